"""Spk2ImgNet -> ONNX, checked against PyTorch (needs the export extra).

- :mod:`.onnx_export`: trace a checkpoint or a random-weight member to one ONNX file
  (``GridSample`` graph, opset 18) and check its contract; :mod:`.deform_conv_graph` makes the
  ``DeformConv`` (opset 19) graph from the same weights; :mod:`.metadata`: its ``metadata_props``.
- :mod:`.hard_cases` and :mod:`.verify`: torch vs onnxruntime parity on simulated scenes and
  hard cases; :mod:`.quantize`: fp16 and int8 variants and their error.
- :mod:`.pipeline`: export followed by validation, the one entry point of CLI, tests and CI.
"""
