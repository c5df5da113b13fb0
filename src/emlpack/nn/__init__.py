"""The eMLP energy model: neighbour lists, SchNet short range, electrostatics, potential."""

from emlpack.nn.graph import Graph, collate
from emlpack.nn.potential import EMLP, ModelConfig

__all__ = ["EMLP", "Graph", "ModelConfig", "collate"]
