"""emlpack: the electron machine learning potential (eMLP) in PyTorch.

The two entry points most users want are importable from here::

    import emlpack
    ensemble = emlpack.load_pretrained("mini-eqm7")
    atoms.calc = emlpack.EMLPCalculator(model="mini-eqm7")   # an ASE calculator

They are loaded on first use, so ``import emlpack`` (and ``emlp --help``) does not import torch.
"""

__version__ = "0.1.0"

#: lazily loaded public names: name -> module that defines it
_LAZY = {
    "load_pretrained": "emlpack.calculators.ensemble",
    "EMLPCalculator": "emlpack.calculators.ase",
}
__all__ = ["__version__", *_LAZY]


def __getattr__(name: str):
    if name in _LAZY:
        import importlib

        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'emlpack' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted([*globals(), *_LAZY])
