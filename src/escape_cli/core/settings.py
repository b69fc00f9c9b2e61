"""The settings records shared by every layer (CLI defaults, training, model metadata, inference); no numpy."""

from __future__ import annotations

from dataclasses import dataclass

from escape_cli.core.params import as_choice, as_count, as_number

METHODS = ("ball", "fps", "cluster")
"""Anchor methods (paper section 3.1 and its ablation)."""


@dataclass(frozen=True)
class AnchorSettings:
    """How anchors are chosen: the one record of it (CLI defaults, training, model metadata, inference).

    Attributes
    ----------
    k : int
        Number of anchors (>= 4 for a 3D reconstruction).
    method : str
        "ball", "fps" or "cluster".
    radius : float
        Search radius of the "ball" refinement, in the network's units (paper: 0.075).
    knn : int
        Neighbourhood size of the curvature estimate.
    """

    k: int = 8
    method: str = "ball"
    radius: float = 0.075
    knn: int = 16

    def __post_init__(self) -> None:
        as_count(self.k, "k (the number of anchors)", minimum=4)
        as_choice(self.method, "the anchor method", METHODS)
        as_number(self.radius, "the anchor radius", above=0.0)
        as_count(self.knn, "the curvature neighbourhood knn", minimum=3)

    @classmethod
    def from_dict(cls, data: dict | None) -> "AnchorSettings":
        """Settings from a metadata record; missing keys take the defaults."""
        data = data or {}
        known = {key: data[key] for key in ("k", "method", "radius", "knn") if key in data}
        return cls(**known)

    def to_dict(self) -> dict:
        return {"k": self.k, "method": self.method, "radius": self.radius, "knn": self.knn}


DEFAULTS = AnchorSettings()
