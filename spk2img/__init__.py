"""spk2img: spike-camera streams to images."""

__version__ = "0.1.0"
