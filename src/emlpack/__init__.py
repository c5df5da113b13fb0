"""emlpack: the electron machine learning potential (eMLP) in PyTorch."""

__version__ = "0.1.0"
