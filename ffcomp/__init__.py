"""ffcomp: model-based feedforward vibration compensation for delta 3D printers."""

__version__ = "0.1.0"
