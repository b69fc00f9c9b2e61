"""Typed network configurations: a `small` preset for CPUs and the authors' `paper` preset."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace


@dataclass(frozen=True)
class ModelConfig:
    """Sizes of the distance-space completion network.

    The network reads (B, N, K) distances of the partial cloud to K anchors, its rows in
    farthest-point order, and predicts (B, Q * fold, K) distances of the complete shape.
    """

    anchors: int = 8  # K
    input_points: int = 2048  # N
    centres_fine: int = 512  # first grouping stage: the N rows' FPS prefix
    centres_coarse: int = 128  # second grouping stage: proxies seen by the transformer
    group_knn: int = 16  # neighbours per centre in the EdgeConv grouping
    embed_dim: int = 64  # per-point embedding before grouping
    dim: int = 256  # transformer width
    heads: int = 4
    encoder_depth: int = 4
    decoder_depth: int = 4
    ffn_ratio: float = 2.0
    predicted_queries: int = 128  # queries regressed from the global feature
    input_queries: int = 128  # queries seeded from the input's own FPS rows
    fold: int = 56  # points rebuilt per query
    rebuild_hidden: int = 128
    positive_output: bool = False  # distances through a sharp softplus: never negative
    refine_stages: int = 0  # coarse-to-fine offset steps after the fold (OffsetRefiner)
    refine_knn: int = 8  # neighbouring queries each refiner looks at

    @property
    def queries(self) -> int:
        return self.predicted_queries + self.input_queries

    @property
    def output_points(self) -> int:
        return self.queries * self.fold

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "ModelConfig":
        known = {f.name for f in fields(cls)}
        return cls(**{k: v for k, v in data.items() if k in known})


PRESETS: dict[str, ModelConfig] = {
    # Trains on 2 CPU cores; predicts 256 x 64 = 16384 points, so a completion never
    # needs to repeat points. (The first shipped model had fold 56 and no softplus.)
    "small": ModelConfig(fold=64, positive_output=True),
    # `small` with two more encoder and decoder layers (9.0 M parameters, +2.6 M); grown from a
    # `small` model by `--init`, its new layers start as the identity.
    "small-deep": ModelConfig(fold=64, positive_output=True, encoder_depth=6, decoder_depth=6),
    # `small` with two coarse-to-fine offset steps after the fold (6.5 M parameters, +0.14 M); grown
    # from a `small` model by `--init`, its refiners start by moving nothing.
    "small-refine": ModelConfig(fold=64, positive_output=True, refine_stages=2),
    # Tiny configurations for tests.
    "tiny": ModelConfig(
        input_points=256, centres_fine=64, centres_coarse=32, group_knn=8, embed_dim=16, dim=32,
        heads=2, encoder_depth=1, decoder_depth=1, predicted_queries=16, input_queries=16, fold=32,
        rebuild_hidden=32, positive_output=True,
    ),
    # The authors' AdaPoinTr-sized configuration (~35 M parameters), for a GPU.
    "paper": ModelConfig(
        centres_fine=512, centres_coarse=256, group_knn=16, embed_dim=64, dim=384, heads=6,
        encoder_depth=6, decoder_depth=8, ffn_ratio=4.0, predicted_queries=256, input_queries=256,
        fold=32, rebuild_hidden=512, positive_output=True,
    ),
}
PRESETS["tiny-refine"] = replace(PRESETS["tiny"], refine_stages=2)


def get_preset(name: str) -> ModelConfig:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown config {name!r}; choose from {', '.join(PRESETS)}") from None
