"""Training loop: DMCD loss, warm-up + cosine schedule, validation, checkpoints, resume."""

from __future__ import annotations

import contextlib
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
from escape_cli.nn.model import EscapeNet, count_parameters, full_precision
from escape_cli.nn.samples import PreparedSplit, concatenate_splits, prepare_split

log = logging.getLogger("escape")

PRECISIONS = ("fp32", "bf16")
"""--precision: float32 throughout, or the forward under bfloat16 autocast (weights, optimizer state, loss fp32)."""


@dataclass(frozen=True)
class TrainOptions:
    """Everything a training run depends on (saved in every checkpoint)."""

    data: str  # the dataset; its val split is the run's validation unless `val_data` names others
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
    augment_noise: float = 0.0  # each sample's input jittered by a sigma drawn from [0, this] (see InputAugmentation)
    augment_density: float = 1.0  # each sample keeps a fraction of its distinct rows drawn from [this, 1]
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
    precision: str = "fp32"  # "bf16": the forward under bfloat16 autocast (runs before this field: fp32)
    cache: str | None = None  # folder of the prepared-data caches (None: OUT/cache)
    val_data: tuple[str, ...] = ()  # validation sets: these datasets' val splits (empty: `data`'s)

    def __post_init__(self):
        InputAugmentation(self.augment_noise, self.augment_density)  # refuses bad values
        if self.precision not in PRECISIONS:
            raise EscapeError(f"unknown precision {self.precision!r} (choose from {', '.join(PRECISIONS)})")

    @property
    def cache_dir(self) -> Path:
        """Where prepared splits are cached: `cache`, or the run folder's cache/."""
        return Path(self.cache) if self.cache else Path(self.out) / "cache"

    @property
    def val_roots(self) -> tuple[str, ...]:
        """The datasets whose val splits validate the run: `val_data`, else `data` alone."""
        return self.val_data or (self.data,)

    @property
    def augmentation(self) -> "InputAugmentation":
        return InputAugmentation(self.augment_noise, self.augment_density)

    @classmethod
    def from_dict(cls, raw: dict) -> "TrainOptions":
        """The options saved in a checkpoint (`asdict` form) back as a `TrainOptions`."""
        values = {key: value for key, value in raw.items() if key in cls.__dataclass_fields__}
        values["anchors"] = AnchorSettings.from_dict(values.get("anchors"))
        # runs from before the partial frame trained in absolute units
        values["frame"] = PartialFrame(**values["frame"]) if values.get("frame") else None
        values["extra_data"] = tuple(values.get("extra_data") or ())
        values["val_data"] = tuple(values.get("val_data") or ())
        values["precision"] = values.get("precision") or "fp32"  # runs from before --precision
        if values.get("categories"):
            values["categories"] = tuple(values["categories"])
        return cls(**values)


@dataclass(frozen=True)
class InputAugmentation:
    """Noise and density of the training inputs, drawn per sample, as real scans vary.

    noise : the largest sigma of Gaussian jitter (network-frame units, where a partial's
        radius is about 0.28); each sample's sigma is drawn uniformly from [0, noise].
    density : the smallest kept fraction of a sample's distinct rows; each sample keeps
        the first m rows (a farthest-point prefix, i.e. a sparser scan of the same
        surface), m drawn from [density, 1] of them but never under `MIN_ROWS`, and is
        refilled cyclically as `prepare_input` refills a short scan. The first
        `MIN_ROWS` rows stay, so the partial's frame and anchors are unchanged.
    The truth is never touched.
    """

    noise: float = 0.0
    density: float = 1.0

    MIN_ROWS = 256  # PartialFrame's rows: the frame is fitted on these

    def __post_init__(self):
        from escape_cli.core.params import as_number

        as_number(self.noise, "augmentation noise", minimum=0.0)
        as_number(self.density, "augmentation density", above=0.0, maximum=1.0)

    @property
    def active(self) -> bool:
        return self.noise > 0 or self.density < 1

    def apply(self, points: np.ndarray, unique_counts: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """points : (B, N, 3) FPS-ordered inputs, unique_counts : (B,) distinct leading rows -> (B, N, 3) new array."""
        out = np.array(points, dtype=np.float32, copy=True)
        n = out.shape[1]
        for b in range(len(out)):
            keep = int(unique_counts[b])
            if self.density < 1 and keep > self.MIN_ROWS:
                keep = max(self.MIN_ROWS, int(round(rng.uniform(self.density, 1.0) * keep)))
            distinct = out[b, :keep]  # (M, 3), a view: jittered before the refill repeats it
            if self.noise > 0:
                distinct += (rng.uniform(0.0, self.noise) * rng.standard_normal(distinct.shape)).astype(np.float32)
            out[b] = distinct[np.arange(n) % keep]
        return out


def distances(points: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """points : (B, N, 3), anchors : (B, K, 3) -> (B, N, K)."""
    return torch.cdist(points, anchors)


def _cpu_has_bf16() -> bool:
    """Whether oneDNN runs bfloat16 natively here (AVX512-BF16 or AMX)."""
    try:
        return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # pragma: no cover - a build without oneDNN
        return False


def validation_split(options: TrainOptions, input_points: int, root: str | None = None) -> PreparedSplit:
    """Validation samples of one dataset (default `data`): the first view of each val object, `val_limit` of them."""
    with cache_lock(options.cache_dir):
        return prepare_split(
            Path(root or options.data), "val", input_points, options.anchors, options.cache_dir, options.frame,
            categories=options.categories, views="first", limit=options.val_limit, workers=options.workers,
        )


def set_names(roots) -> list[str]:
    """The names of validation sets in curve.csv: their folder names (refused when two are alike)."""
    names = [Path(root).resolve().name or str(root) for root in roots]
    for name in names:
        if names.count(name) > 1:
            raise EscapeError(f"two validation sets are named {name!r}: give them folders of different names")
    return names


def validation_sets(options: TrainOptions, input_points: int) -> dict[str, PreparedSplit]:
    """The run's validation splits by set name (see `set_names`), in the order given."""
    roots = options.val_roots
    return {name: validation_split(options, input_points, root) for name, root in zip(set_names(roots), roots)}


@contextlib.contextmanager
def cache_lock(folder: Path):
    """Hold FOLDER/.lock while preparing or reading caches there: runs sharing a cache take turns.

    A second run that needs a split the first is preparing waits for it and then reads
    it from the cache instead of preparing it again. (The files themselves are written
    to a temporary name and renamed, so a reader never sees half of one.) Without
    `fcntl` (Windows) there is no lock.
    """
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / ".lock", "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.info("waiting for another run preparing data in %s", folder)
            fcntl.flock(fh, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def sample_batch(data: PreparedSplit, idx: np.ndarray, rng: np.random.Generator, gt_points: int, noise: float, device,
                 augmentation: InputAugmentation | None = None, augment_rng: np.random.Generator | None = None):
    """Rows `idx` of a split: (B, N, K) input and (B, G, K) truth distances, then the xyz of input, anchors, truth.

    Everything is in each sample's network frame (the truth mapped like its partial).
    An active `augmentation` changes the inputs with draws from `augment_rng` (its own
    generator, so the batches, truth subsets and fold seeds stay those of a run without it).
    """
    inputs = data.inputs[idx]  # (B, N, 3)
    if augmentation is not None and augmentation.active:
        inputs = augmentation.apply(inputs, data.unique_counts[idx], augment_rng)
    pts = torch.from_numpy(inputs).to(device)  # (B, N, 3)
    anc = torch.from_numpy(data.anchors[idx]).to(device)  # (B, K, 3)
    if noise > 0:
        pts = pts + noise * torch.from_numpy(rng.standard_normal(pts.shape).astype(np.float32)).to(device)
    m = data.completes.shape[1]
    rows = [rng.choice(m, min(gt_points, m), replace=False) for _ in idx]  # B x (G,)
    gt = np.stack([data.complete_in_frame(i, r) for i, r in zip(idx, rows)])  # (B, G, 3)
    gt = torch.from_numpy(gt).to(device)
    return distances(pts, anc), distances(gt, anc), pts, anc, gt


class _Laps:
    """Adds the seconds since the previous lap to `times[name]` (nothing when `times` is None)."""

    def __init__(self, times: dict | None):
        self.times = times
        self.last = time.perf_counter()

    def __call__(self, name: str) -> None:
        if self.times is None:
            return
        if torch.cuda.is_available() and torch.cuda.is_initialized():
            torch.cuda.synchronize()
        now = time.perf_counter()
        self.times[name] = self.times.get(name, 0.0) + now - self.last
        self.last = now


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
        if options.precision == "bf16" and self.device.type == "cpu" and not _cpu_has_bf16():
            log.warning("this CPU has no bfloat16 instructions (AVX512-BF16 or AMX): --precision bf16 is emulated and much slower: use --precision fp32")
        self.config: ModelConfig = get_preset(options.config)
        torch.manual_seed(options.seed)
        self.model = EscapeNet(self.config).to(self.device)
        # fused: one kernel over all parameters (~2x faster than the per-tensor loop; the same update to rounding)
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=options.lr, weight_decay=options.weight_decay, fused=True)
        self.step = 0
        self.epoch = 0
        self.elapsed = 0.0
        self.best = math.inf
        self.lineage: list[dict] = []  # runs this one was initialised from, oldest first
        self.last_metrics: dict = {}  # of the latest validation
        self.last_step_seconds = 0.0
        self.stage_times: dict | None = None  # a dict: gains each stage's seconds (see train_step)
        self._losses: list[float] = []  # training losses since the latest validation
        with cache_lock(options.cache_dir):
            self.train_data: PreparedSplit = concatenate_splits([
                prepare_split(
                    Path(root), "train", self.config.input_points, options.anchors, options.cache_dir, options.frame,
                    categories=options.categories, max_views=options.views_per_object, workers=options.workers,
                )
                for root in (options.data, *options.extra_data)
            ])
        self.val_sets: dict[str, PreparedSplit] = validation_sets(options, self.config.input_points)
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
        saved = TrainOptions.from_dict({"data": "", "out": "", **state.get("options", {})})
        if set_names(saved.val_roots) != list(self.val_sets):
            raise EscapeError(
                f"cannot resume: the run in {self.out} validates on {', '.join(set_names(saved.val_roots))}, "
                f"not on {', '.join(self.val_sets)} (its curve and best.pt compare those)"
            )
        self.model.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        for group in self.optimizer.param_groups:  # a checkpoint from before the fused update names the loop
            group.update(fused=True, foreach=None)
        self.step, self.epoch = state["step"], state["epoch"]
        self.elapsed, self.best = state["elapsed"], state["best"]
        self.lineage = state.get("lineage", [])
        log.info("resumed from %s at step %d (epoch %d, precision %s)", path, self.step, self.epoch, self.opt.precision)

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
        workers = torch.get_num_threads()  # the network waits for the loss: its threads are free
        fine_loss = chamfer_l1(pred, d_gt, workers=workers)
        coarse_loss = chamfer_l1(coarse, d_gt[:, : self.opt.coarse_gt_points], workers=workers)
        return fine_loss + self.opt.coarse_weight * coarse_loss, fine_loss

    @property
    def val_data(self) -> PreparedSplit:
        """The first validation set (the only one unless --val-data names several)."""
        return next(iter(self.val_sets.values()))

    def autocast(self):
        """The forward's precision: bfloat16 autocast for --precision bf16, else nothing."""
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.opt.precision == "bf16")

    def _xyz_loss(self, fine, pts, anc, gt):
        """Chamfer-L1 in xyz of the reconstructed fine output (+ observed points) against the truth."""
        rec = reconstruct_differentiable(fine, anc, pts.detach().cpu().double().numpy(), workers=torch.get_num_threads())  # (B, P, 3)
        pred = torch.cat([rec, pts], dim=1) if self.opt.include_observed else rec
        return chamfer_l1(pred, gt, self.opt.recall_weight, workers=torch.get_num_threads())

    def train_step(self, idx: np.ndarray, rng: np.random.Generator, times: dict | None = None) -> float:
        """One optimizer step on the samples `idx`; returns the loss.

        `times`, when given, gains the seconds of each stage (added to what it holds):
        sample, forward, loss (DMCD), xyz (solve and xyz Chamfer), backward, optimizer.
        """
        lap = _Laps(times)
        self.model.train()
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr_at(self.step)
        d_in, d_gt, pts, anc, gt = sample_batch(
            self.train_data, idx, rng, self.opt.gt_points, self.opt.denoise_sigma, self.device,
            self.opt.augmentation, np.random.default_rng((self.opt.seed, self.step, 2)),
        )
        seed_index = torch.from_numpy(np.sort(rng.choice(self.config.fold, min(self.opt.fold_subset, self.config.fold), replace=False)))
        lap("sample")
        with self.autocast():
            fine, coarse = self.model(d_in, seed_index.to(self.device))
        fine, coarse = full_precision(fine), full_precision(coarse)  # the loss in float32
        lap("forward")
        loss, _ = self._loss(d_in, d_gt, fine, coarse)
        lap("loss")
        if self.opt.xyz_weight > 0:
            loss = loss + self.opt.xyz_weight * self._xyz_loss(fine, pts, anc, gt)
            lap("xyz")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        lap("backward")
        torch.nn.utils.clip_grad_norm_(self.model.parameters(), 1.0)
        self.optimizer.step()
        self.step += 1
        value = float(loss.item())
        lap("optimizer")
        return value

    # -- validation ---------------------------------------------------------------------
    def validate(self) -> dict:
        """Distance-space CD-L1 on the val split(s) and xyz CD-L1 after reconstruction on a subset (float32)."""
        return validate_sets(self.model, self.val_sets, self.opt, self.device)

    def _log_curve(self, row: dict) -> None:
        path = self.out / "curve.csv"
        new = not path.exists()
        with path.open("a", newline="") as fh:
            writer = csv.DictWriter(fh, fieldnames=list(row))
            if new:
                writer.writeheader()
            writer.writerow(row)

    # -- the loop -----------------------------------------------------------------------
    def run(self, progress_callback=None, steps: int | None = None) -> dict:
        """Train to the end of the schedule, or `steps` more steps (then call again to go on); returns the last validation's metrics.

        `progress_callback(step, total, loss, metrics)` is called after every step, once
        that step's validation (if one was due) is done: `metrics` is the latest
        validation's dict, a new one after each validation. Each step's seconds are in
        `last_step_seconds`; with `stage_times` set to a dict, it gains each stage's
        seconds (see `train_step`).
        """
        o = self.opt
        total_steps = self.total_steps
        stop = total_steps if steps is None else min(total_steps, self.step + steps)
        while self.step < stop:
            self.epoch = self.step // self.steps_per_epoch
            pos = self.step % self.steps_per_epoch
            order = np.random.default_rng((o.seed, self.epoch)).permutation(len(self.train_data))
            idx = order[pos * o.batch : (pos + 1) * o.batch]
            rng = np.random.default_rng((o.seed, self.step, 1))
            t0 = time.perf_counter()
            loss = self.train_step(idx, rng, self.stage_times)
            self._losses.append(loss)
            self.last_step_seconds = time.perf_counter() - t0
            self.elapsed += self.last_step_seconds
            end_of_epoch = self.step % self.steps_per_epoch == 0
            due = (o.val_every and self.step % o.val_every == 0) or end_of_epoch or self.step == total_steps
            if due:
                self.last_metrics = self.validate()
                row = {
                    "step": self.step, "epoch": self.step / self.steps_per_epoch,
                    "train_loss_x1000": 1000 * float(np.mean(self._losses)), **self.last_metrics,
                    "lr": self.lr_at(self.step), "train_seconds": round(self.elapsed, 1),
                }
                self._log_curve(row)
                self._losses = []
                score = self.last_metrics["val_xyz_cd_l1_x1000"]
                if score < self.best:
                    self.best = score
                    self._save("best.pt", {"metrics": row})
                self._save("last.pt", {"metrics": row})
            elif self.step % o.checkpoint_every == 0:
                self._save("last.pt")
            if o.snapshot_every and self.step % o.snapshot_every == 0:
                self._save_snapshot()
            if progress_callback:  # after the step's validation: a due step reports its own metrics
                progress_callback(self.step, total_steps, loss, self.last_metrics)
        return self.last_metrics

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
            rec = reconstruct(fine[j].cpu().double().numpy(), anchors, reference_points=data.inputs[i],
                              workers=torch.get_num_threads()).points
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


def validate_sets(model: EscapeNet, sets: dict[str, PreparedSplit], opt: TrainOptions, device: torch.device) -> dict:
    """`validate` on each validation set; with several, one score over them all.

    One set: `validate`'s three numbers, named as they are. Several: each set's three
    with ``@<set name>`` appended (``val_xyz_cd_l1_x1000@modelnet40``), and first the
    selection score ``val_xyz_cd_l1_x1000`` = mean over the sets of (the set's xyz CD-L1
    / its input-copy CD-L1): not a distance but the mean share of the input copy's error
    that remains (0.55: x0.55), so sets of different difficulty weigh the same.
    """
    if len(sets) == 1:
        return validate(model, next(iter(sets.values())), opt, device)
    per_set, ratios = {}, []
    for name, data in sets.items():
        metrics = validate(model, data, opt, device)
        per_set.update({f"{key}@{name}": value for key, value in metrics.items()})
        ratios.append(metrics["val_xyz_cd_l1_x1000"] / metrics["val_input_cd_l1_x1000"])
    return {"val_xyz_cd_l1_x1000": float(np.mean(ratios)), **per_set}


def saved_options(out: Path) -> dict:
    """The options of the run in OUT (its last.pt), as saved; {} when there is none."""
    path = Path(out) / "last.pt"
    if not path.exists():
        return {}
    try:
        return torch.load(path, map_location="cpu", weights_only=False).get("options", {})
    except Exception as err:  # torch raises many kinds for a bad file
        raise EscapeError(f"cannot read {path}: {err}") from None


def grown_state_dict(model: EscapeNet, config: ModelConfig, seed: int, path) -> dict:
    """`model`'s weights for a network of `config`: equal configs, or one that only grows.

    A network may grow by fold seeds, the softplus, transformer layers and refiners. New
    fold seeds are copies of randomly chosen old ones plus a little noise (so new points
    start where old ones were and spread with training); the softplus changes distances
    above 0.05 by less than 7e-5. New encoder and decoder layers go after the old ones
    with their residual branches' output projections zeroed: pre-norm layers, so each
    starts as the identity. New refiners start with a zero offset layer. Either way the
    grown network computes what the old one did.
    """
    old = model.config
    if old == config:
        return model.state_dict()
    layers = ("encoder_depth", "decoder_depth", "refine_stages")
    counts = ("fold",) + layers  # these may only grow
    grows = counts + ("positive_output",)
    same_otherwise = ModelConfig.from_dict({**old.to_dict(), **{name: getattr(config, name) for name in grows}})
    if same_otherwise != config or any(getattr(config, name) < getattr(old, name) for name in counts):
        raise EscapeError(f"--init {path} holds another network ({old}) than the one asked for ({config})")
    state = model.state_dict()
    seeds = state["rebuild.seeds"]  # (F_old, H)
    extra = config.fold - old.fold
    gen = torch.Generator().manual_seed(seed)
    if extra:
        pick = torch.randint(old.fold, (extra,), generator=gen)
        noise = 0.05 * seeds.std() * torch.randn(extra, seeds.shape[1], generator=gen)
        state["rebuild.seeds"] = torch.cat([seeds, seeds[pick] + noise])  # (F, H)
    if any(getattr(config, name) != getattr(old, name) for name in layers):
        state = {**_new_layers(config, old, gen), **state}
    return state


def _new_layers(config: ModelConfig, old: ModelConfig, gen: torch.Generator) -> dict:
    """Weights of the transformer layers and refiners `config` has beyond `old`'s, each adding nothing at first."""
    with torch.random.fork_rng():  # the caller's global generator is left as it was
        torch.manual_seed(int(torch.randint(2**31 - 1, (1,), generator=gen)))
        fresh = EscapeNet(config).state_dict()
    new = {}
    for stack, depth in (("encoder", old.encoder_depth), ("decoder", old.decoder_depth), ("refine", old.refine_stages)):
        for key, value in fresh.items():
            parts = key.split(".")
            if parts[0] != stack or int(parts[1]) < depth:
                continue
            if parts[2] in ("self_attn", "multihead_attn") and parts[3] == "out_proj" or parts[2] == "linear2":
                value = torch.zeros_like(value)  # the branch adds nothing until trained
            new[key] = value
    return new
