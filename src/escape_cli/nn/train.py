"""Training loop: DMCD loss, warm-up + cosine schedule, validation, checkpoints, resume."""

from __future__ import annotations

import csv
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from escape_cli.core.normalize import PartialFrame
from escape_cli.core.settings import AnchorSettings
from escape_cli.errors import EscapeError
from escape_cli.nn.checkpoint import load_checkpoint_model, save_checkpoint
from escape_cli.nn.config import ModelConfig, get_preset
from escape_cli.nn.loss import chamfer_l1, reconstruct_differentiable
from escape_cli.nn.model import EscapeNet, count_parameters
from escape_cli.nn.samples import PreparedSplit, concatenate_splits, prepare_split

log = logging.getLogger("escape")


@dataclass(frozen=True)
class TrainOptions:
    """Everything a training run depends on (saved in every checkpoint)."""

    data: str  # the dataset; its val split is the run's validation
    out: str
    config: str = "small"
    epochs: int = 10
    batch: int = 8
    lr: float = 5e-4
    weight_decay: float = 5e-4
    warmup_steps: int = 300
    min_lr_ratio: float = 0.02
    seed: int = 0
    device: str = "cpu"
    gt_points: int = 2048  # ground-truth subsample per step for the loss
    coarse_gt_points: int = 512
    fold_subset: int = 8  # rebuilt points per query used per step (of `fold`)
    views_per_object: int | None = None  # train on the first V views of each object (None: all)
    coarse_weight: float = 1.0
    include_observed: bool = True  # the input's own rows join the prediction in the loss
    denoise_sigma: float = 0.0  # Gaussian jitter on input points; the target stays clean
    xyz_weight: float = 0.0  # weight of Chamfer-L1 in xyz after reconstruction (0: DMCD only)
    recall_weight: float = 1.0  # weight of the xyz term's truth -> prediction half (1: symmetric)
    val_every: int = 0  # steps between validations (0: once per epoch)
    val_limit: int = 400
    xyz_val_samples: int = 24
    checkpoint_every: int = 200
    snapshot_every: int = 0  # keep the weights every N steps in OUT/snapshots (0: never), for `escape average-checkpoints`
    workers: int = 2
    threads: int = 0  # torch threads (0: torch's default)
    categories: tuple[str, ...] | None = None
    max_steps: int | None = None  # stop early (tests, smoke runs)
    init: str | None = None  # start from this checkpoint's weights (fresh optimizer and schedule)
    anchors: AnchorSettings = field(default_factory=AnchorSettings)
    frame: PartialFrame | None = field(default_factory=PartialFrame)  # None: absolute dataset units
    extra_data: tuple[str, ...] = ()  # more datasets whose train splits join `data`'s

    @classmethod
    def from_dict(cls, raw: dict) -> "TrainOptions":
        """The options saved in a checkpoint (`asdict` form) back as a `TrainOptions`."""
        values = {key: value for key, value in raw.items() if key in cls.__dataclass_fields__}
        values["anchors"] = AnchorSettings.from_dict(values.get("anchors"))
        # runs from before the partial frame trained in absolute units
        values["frame"] = PartialFrame(**values["frame"]) if values.get("frame") else None
        values["extra_data"] = tuple(values.get("extra_data") or ())
        if values.get("categories"):
            values["categories"] = tuple(values["categories"])
        return cls(**values)


def distances(points: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """points : (B, N, 3), anchors : (B, K, 3) -> (B, N, K)."""
    return torch.cdist(points, anchors)


def validation_split(options: TrainOptions, input_points: int) -> PreparedSplit:
    """The run's validation samples: the first view of each val object, `val_limit` of them."""
    return prepare_split(
        Path(options.data), "val", input_points, options.anchors, Path(options.out) / "cache", options.frame,
        categories=options.categories, views="first", limit=options.val_limit, workers=options.workers,
    )


def sample_batch(data: PreparedSplit, idx: np.ndarray, rng: np.random.Generator, gt_points: int, noise: float, device):
    """Rows `idx` of a split: (B, N, K) input and (B, G, K) truth distances, then the xyz of input, anchors, truth.

    Everything is in each sample's network frame (the truth mapped like its partial).
    """
    pts = torch.from_numpy(data.inputs[idx]).to(device)  # (B, N, 3)
    anc = torch.from_numpy(data.anchors[idx]).to(device)  # (B, K, 3)
    if noise > 0:
        pts = pts + noise * torch.from_numpy(rng.standard_normal(pts.shape).astype(np.float32)).to(device)
    m = data.completes.shape[1]
    rows = [rng.choice(m, min(gt_points, m), replace=False) for _ in idx]  # B x (G,)
    gt = np.stack([data.complete_in_frame(i, r) for i, r in zip(idx, rows)])  # (B, G, 3)
    gt = torch.from_numpy(gt).to(device)
    return distances(pts, anc), distances(gt, anc), pts, anc, gt


class Trainer:
    """Holds the model, data and state of one run; `run()` trains until the last epoch."""

    def __init__(self, options: TrainOptions, resume: bool = False):
        self.opt = options
        self.out = Path(options.out)
        self.out.mkdir(parents=True, exist_ok=True)
        if options.threads:
            torch.set_num_threads(options.threads)
        self.device = torch.device(options.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise EscapeError("--device cuda was asked for but no CUDA device is available")
        self.config: ModelConfig = get_preset(options.config)
        torch.manual_seed(options.seed)
        self.model = EscapeNet(self.config).to(self.device)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=options.lr, weight_decay=options.weight_decay)
        self.step = 0
        self.epoch = 0
        self.elapsed = 0.0
        self.best = math.inf
        self.lineage: list[dict] = []  # runs this one was initialised from, oldest first
        self.train_data: PreparedSplit = concatenate_splits([
            prepare_split(
                Path(root), "train", self.config.input_points, options.anchors, self.out / "cache", options.frame,
                categories=options.categories, max_views=options.views_per_object, workers=options.workers,
            )
            for root in (options.data, *options.extra_data)
        ])
        self.val_data: PreparedSplit = validation_split(options, self.config.input_points)
        self.steps_per_epoch = max(1, len(self.train_data) // options.batch)
        self.input_radius = self._median_input_radius() if options.frame is None else None
        if resume:
            self._load(self.out / "last.pt")
        elif options.init:
            self._init_weights(Path(options.init))
        (self.out / "options.json").write_text(json.dumps(asdict(options), indent=2, default=str))

    def _median_input_radius(self, count: int = 512) -> float:
        """Median radius of training partials in absolute units: the scale an absolute-frame model's `--normalize auto` maps scans to."""
        from escape_cli.core.normalize import cloud_radius

        data = self.train_data
        rows = np.linspace(0, len(data) - 1, min(count, len(data))).astype(int)
        return float(np.median([cloud_radius(data.inputs[i, : data.unique_counts[i]]) for i in rows]))

    # -- schedule and state -------------------------------------------------------------
    @property
    def total_steps(self) -> int:
        """Steps of the whole run: `epochs` worth, or `max_steps` when that is sooner."""
        total = self.opt.epochs * self.steps_per_epoch
        return total if self.opt.max_steps is None else min(total, self.opt.max_steps)

    def lr_at(self, step: int) -> float:
        """Linear warm-up, then cosine decay to `min_lr_ratio` at `total_steps`."""
        o = self.opt
        total = max(self.total_steps, o.warmup_steps + 1)
        if step < o.warmup_steps:
            return o.lr * (step + 1) / o.warmup_steps
        progress = min(1.0, (step - o.warmup_steps) / max(1, total - o.warmup_steps))
        return o.lr * (o.min_lr_ratio + (1 - o.min_lr_ratio) * 0.5 * (1 + math.cos(math.pi * progress)))

    def _state(self) -> dict:
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "step": self.step,
            "epoch": self.epoch,
            "elapsed": self.elapsed,
            "best": self.best,
            "config": self.config.to_dict(),
            "options": asdict(self.opt),
            "anchors": asdict(self.opt.anchors),
            "parameters": count_parameters(self.model),
            "train_samples": len(self.train_data),
            "train_objects": len(self.train_data.completes),
            "steps_per_epoch": self.steps_per_epoch,
            "input_radius": self.input_radius,
            "frame": None if self.opt.frame is None else self.opt.frame.to_dict(),
            "lineage": self.lineage,
        }

    def _save(self, name: str, extra: dict | None = None) -> None:
        state = self._state()
        state.update(extra or {})
        save_checkpoint(state, self.out / name)

    def _load(self, path: Path) -> None:
        if not path.exists():
            raise EscapeError(f"cannot resume: {path} does not exist")
        state = torch.load(path, map_location=self.device, weights_only=False)
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.step, self.epoch = state["step"], state["epoch"]
        self.elapsed, self.best = state["elapsed"], state["best"]
        self.lineage = state.get("lineage", [])
        log.info("resumed from %s at step %d (epoch %d)", path, self.step, self.epoch)

    def _init_weights(self, path: Path) -> None:
        model, state = load_checkpoint_model(path)
        options = state.get("options", {})
        self.model.load_state_dict(grown_state_dict(model, self.config, self.opt.seed, path))
        self.lineage = state.get("lineage", []) + [{
            "checkpoint": str(path), "steps": state["step"], "train_seconds": round(state.get("elapsed", 0.0), 1),
            "lr": options.get("lr"), "xyz_weight": options.get("xyz_weight", 0.0),
            "recall_weight": options.get("recall_weight", 1.0),
        }]
        log.info("initialised from %s (step %d)", path, state["step"])

    # -- one batch ----------------------------------------------------------------------
    def _loss(self, d_in, d_gt, fine, coarse):
        pred = torch.cat([fine, d_in], dim=1) if self.opt.include_observed else fine
        fine_loss = chamfer_l1(pred, d_gt)
        coarse_loss = chamfer_l1(coarse, d_gt[:, : self.opt.coarse_gt_points])
        return fine_loss + self.opt.coarse_weight * coarse_loss, fine_loss

    def _xyz_loss(self, fine, pts, anc, gt):
        """Chamfer-L1 in xyz of the reconstructed fine output (+ observed points) against the truth."""
        rec = reconstruct_differentiable(fine, anc, pts.detach().cpu().double().numpy())  # (B, P, 3)
        pred = torch.cat([rec, pts], dim=1) if self.opt.include_observed else rec
        return chamfer_l1(pred, gt, self.opt.recall_weight)

    def train_step(self, idx: np.ndarray, rng: np.random.Generator) -> float:
        self.model.train()
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr_at(self.step)
        d_in, d_gt, pts, anc, gt = sample_batch(
            self.train_data, idx, rng, self.opt.gt_points, self.opt.denoise_sigma, self.device
        )
        seed_index = torch.from_numpy(np.sort(rng.choice(self.config.fold, min(self.opt.fold_subset, self.config.fold), replace=False)))
        fine, coarse = self.model(d_in, seed_index.to(self.device))
        loss, _ = self._loss(d_in, d_gt, fine, coarse)
        if self.opt.xyz_weight > 0:
            loss = loss + self.opt.xyz_weight * self._xyz_loss(fine, pts, anc, gt)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
        self.optimizer.step()
        self.step += 1
        return float(loss.item())

    # -- validation ---------------------------------------------------------------------
    def validate(self) -> dict:
        """Distance-space CD-L1 on the val split and xyz CD-L1 after reconstruction on a subset."""
        return validate(self.model, self.val_data, self.opt, self.device)

    def _log_curve(self, row: dict) -> None:
        path = self.out / "curve.csv"
        new = not path.exists()
        with path.open("a", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(row))
            if new:
                writer.writeheader()
            writer.writerow(row)

    # -- the loop -----------------------------------------------------------------------
    def run(self, progress_callback=None) -> dict:
        o = self.opt
        last_metrics: dict = {}
        losses: list[float] = []
        total_steps = self.total_steps
        while self.step < total_steps:
            self.epoch = self.step // self.steps_per_epoch
            pos = self.step % self.steps_per_epoch
            order = np.random.default_rng((o.seed, self.epoch)).permutation(len(self.train_data))
            idx = order[pos * o.batch : (pos + 1) * o.batch]
            rng = np.random.default_rng((o.seed, self.step, 1))
            t0 = time.perf_counter()
            losses.append(self.train_step(idx, rng))
            self.elapsed += time.perf_counter() - t0
            end_of_epoch = self.step % self.steps_per_epoch == 0
            due = (o.val_every and self.step % o.val_every == 0) or end_of_epoch or self.step == total_steps
            if progress_callback:
                progress_callback(self.step, total_steps, losses[-1], last_metrics)
            if due:
                last_metrics = self.validate()
                row = {
                    "step": self.step, "epoch": self.step / self.steps_per_epoch,
                    "train_loss_x1000": 1000 * float(np.mean(losses)), **last_metrics,
                    "lr": self.lr_at(self.step), "train_seconds": round(self.elapsed, 1),
                }
                self._log_curve(row)
                losses = []
                score = last_metrics["val_xyz_cd_l1_x1000"]
                if score < self.best:
                    self.best = score
                    self._save("best.pt", {"metrics": row})
                self._save("last.pt", {"metrics": row})
            elif self.step % o.checkpoint_every == 0:
                self._save("last.pt")
            if o.snapshot_every and self.step % o.snapshot_every == 0:
                self._save_snapshot()
        return last_metrics

    def _save_snapshot(self) -> None:
        """Weights and metadata of this step (no optimizer state) as OUT/snapshots/step<N>.pt."""
        state = {key: value for key, value in self._state().items() if key != "optimizer"}
        folder = self.out / "snapshots"
        folder.mkdir(exist_ok=True)
        save_checkpoint(state, folder / f"step{self.step:07d}.pt")


@torch.no_grad()
def validate(model: EscapeNet, data: PreparedSplit, opt: TrainOptions, device: torch.device) -> dict:
    """Distance-space CD-L1 on a prepared split and xyz CD-L1 after reconstruction on a spread subset.

    The same ground-truth subsets every call (fixed seed), so numbers compare across steps and runs.
    The xyz numbers are in the dataset's units (PCN units), whatever the network's frame.
    """
    from escape_cli.core.metrics import chamfer_l1 as xyz_chamfer_l1
    from escape_cli.core.reconstruction import reconstruct

    model.eval()
    rng = np.random.default_rng(12345)
    dmcd = []
    xyz, baseline = [], []
    # xyz subset spread over the split (it is sorted by category)
    xyz_rows = set(np.linspace(0, len(data) - 1, min(opt.xyz_val_samples, len(data))).astype(int).tolist())
    for start in range(0, len(data), opt.batch):
        idx = np.arange(start, min(len(data), start + opt.batch))
        d_in, d_gt, *_ = sample_batch(data, idx, rng, opt.gt_points, 0.0, device)
        fine, coarse = model(d_in)
        pred = torch.cat([fine, d_in], dim=1) if opt.include_observed else fine
        dmcd.append(chamfer_l1(pred, d_gt).item() * len(idx))
        for j, i in enumerate(idx):
            if i not in xyz_rows:
                continue
            anchors = data.anchors[i].astype(np.float64)
            rec = reconstruct(fine[j].cpu().double().numpy(), anchors, reference_points=data.inputs[i]).points
            observed = data.inputs[i].astype(np.float64)
            out = np.concatenate([rec, observed]) if opt.include_observed else rec
            truth = data.complete_in_frame(i).astype(np.float64)
            scale = float(data.scales[i])  # metrics in the dataset's units, comparable across frames
            xyz.append(scale * xyz_chamfer_l1(out, truth))
            baseline.append(scale * xyz_chamfer_l1(observed, truth))
    return {
        "val_dmcd_x1000": 1000 * sum(dmcd) / len(data),
        "val_xyz_cd_l1_x1000": 1000 * float(np.mean(xyz)) if xyz else float("nan"),
        "val_input_cd_l1_x1000": 1000 * float(np.mean(baseline)) if baseline else float("nan"),
    }


def grown_state_dict(model: EscapeNet, config: ModelConfig, seed: int, path) -> dict:
    """`model`'s weights for a network of `config`: equal configs, or one that only adds fold seeds / the softplus.

    New fold seeds are copies of randomly chosen old ones plus a little noise (so new
    points start where old ones were and spread with training); the softplus changes
    distances above 0.05 by less than 7e-5.
    """
    old = model.config
    if old == config:
        return model.state_dict()
    same_otherwise = ModelConfig.from_dict({**old.to_dict(), "fold": config.fold, "positive_output": config.positive_output})
    if same_otherwise != config or config.fold < old.fold:
        raise EscapeError(f"--init {path} holds another network ({old}) than the one asked for ({config})")
    state = model.state_dict()
    seeds = state["rebuild.seeds"]  # (F_old, H)
    extra = config.fold - old.fold
    if extra:
        gen = torch.Generator().manual_seed(seed)
        pick = torch.randint(old.fold, (extra,), generator=gen)
        noise = 0.05 * seeds.std() * torch.randn(extra, seeds.shape[1], generator=gen)
        state["rebuild.seeds"] = torch.cat([seeds, seeds[pick] + noise])  # (F, H)
    return state
