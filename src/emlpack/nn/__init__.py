"""The eMLP energy model: neighbour lists, short-range families (SchNet, ...),
electrostatics, potential."""

from emlpack.nn.graph import Graph, collate
from emlpack.nn.potential import EMLP, ModelConfig

__all__ = ["EMLP", "Graph", "ModelConfig", "collate"]
