"""Spikes to frames at inference time (numpy; onnxruntime or torch only when a model loads).

The flow: :mod:`.windows` picks the centres and their frame windows from the model's geometry;
:mod:`.stream` feeds frames through a streaming reconstructor (TFP, TFI, the network on whole
windows); :mod:`.block_stream` and :mod:`.block_codec` encode each shared block once;
:mod:`.adaptive` runs the network only where needed; :mod:`.binning` merges frames of dim
streams; :mod:`.methods` builds the right reconstructor for a method; :mod:`.loader` loads a
model (:mod:`.onnx_backend` or :mod:`.torch_backend`) ready to run; :mod:`.classical` gives
TFP and TFI on whole arrays.
"""
