"""emlpack: the electron machine learning potential (eMLP) in PyTorch."""

__version__ = "0.1.0"


def __getattr__(name: str):
    # lazy, so that `import emlpack` (and `emlp --help`) does not import torch
    if name == "load_pretrained":
        from emlpack.calculators.ensemble import load_pretrained

        return load_pretrained
    raise AttributeError(f"module 'emlpack' has no attribute {name!r}")
