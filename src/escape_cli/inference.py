"""Loading a shipped ONNX model with its metadata and running it with onnxruntime (no torch)."""

from __future__ import annotations

import hashlib
import json
import os
import threading
from concurrent.futures import Future
from pathlib import Path

import escape_cli.packaged_models as packaged_models
from escape_cli.core.settings import AnchorSettings
from escape_cli.errors import EscapeError, ModelError
from escape_cli.model_check import check_against_network, read_signature

MODEL_ENV = packaged_models.MODEL_ENV
SPINNING = False
"""Whether onnxruntime's idle threads spin after a forward pass. Measured on 2 busy cores
(chair, 2 threads): spinning made the forward 2.1x slower (378 vs 177 ms) and the numpy
stages after it 1.5x slower, as the spinning thread takes the core they need."""


def default_model_path() -> Path:
    """The model `escape complete` uses without `--model`.

    $ESCAPE_MODEL when set (a path or a packaged model's name), else the packaged
    model ``small`` (``escape_cli/models/escape-small.onnx``, package data): see
    `escape_cli.packaged_models`.
    """
    return packaged_models.resolve(None)


def model_path(model: str | os.PathLike | None) -> Path:
    """The model file a `--model` value names: a path, a packaged model's name (``synth``), or None for the default."""
    return packaged_models.resolve(model)


class CompletionModel:
    """An exported network: (B, N, K) partial distances -> (B, M, K) complete distances.

    The metadata is read at once; the session (the file read once, its checksum checked,
    then built by onnxruntime) is built on construction, or joined when `preload_model`
    started it, and waited for on first use, so a caller can prepare its input meanwhile.
    """

    def __init__(self, path: Path, threads: int = 0):
        self.path = Path(path)
        self.meta = read_metadata(self.path)
        self._session = _session_loading(str(self.path), threads, background=False)
        if self.failed:  # built here and refused: say so now
            self._session.result()
        self.input_name = self.meta.get("input_name", "partial_distances")
        self.output_name = self.meta.get("output_name", "distances")

    @property
    def k(self) -> int:
        return int(self.meta["k"])

    @property
    def input_points(self) -> int:
        return int(self.meta["input_points"])

    @property
    def output_points(self) -> int:
        return int(self.meta["output_points"])

    @property
    def merge_observed(self) -> bool:
        return bool(self.meta.get("merge_observed", True))

    @property
    def target_radius(self) -> float | None:
        """Absolute-frame models: the training partials' median radius (`--normalize auto`)."""
        value = (self.meta.get("normalization") or {}).get("target_radius")
        return None if value is None else float(value)

    @property
    def frame(self):
        """The `PartialFrame` the model works in, or None for a model trained in absolute PCN units."""
        from escape_cli.core.normalize import PartialFrame

        frame = self.meta.get("frame") or {}
        if frame.get("kind") != "partial":
            return None
        try:
            return PartialFrame(int(frame["rows"]), float(frame["radius"]))
        except (KeyError, TypeError, ValueError):
            raise ModelError(f"{self.path.with_suffix('.json')}: bad 'frame' record {frame}") from None

    @property
    def session(self):
        """The onnxruntime session (waits for a load under way; ModelError if it failed)."""
        return self._session.result()

    @property
    def failed(self) -> bool:
        """Whether building the session has ended in an error."""
        return self._session.done() and self._session.exception() is not None

    @property
    def anchors(self) -> AnchorSettings:
        """How the model's anchors are chosen (its metadata; defaults where it is silent)."""
        try:
            return AnchorSettings.from_dict({"k": self.k, **(self.meta.get("anchors") or {})})
        except EscapeError as err:
            raise ModelError(f"{self.path.with_suffix('.json')}: bad anchor settings: {err}") from None

    def predict(self, partial_distances):
        """partial_distances : (B, N, K) -> (B, M, K) float32 array."""
        import numpy as np

        x = np.ascontiguousarray(partial_distances, dtype=np.float32)
        if x.ndim != 3 or x.shape[1:] != (self.input_points, self.k):
            raise ModelError(f"model expects (B, {self.input_points}, {self.k}) distances, got {x.shape}")
        try:
            return self.session.run([self.output_name], {self.input_name: x})[0]
        except Exception as err:
            raise ModelError(f"running {self.path.name} failed: {err}") from None


def read_metadata(path: Path) -> dict:
    """The JSON beside a model file, checked for the fields inference needs.

    Cheap (no onnxruntime): commands call it before any work, so that a wrong model path
    is reported first.

    Raises
    ------
    ModelError
        `path` is missing, a folder, empty or not an ``.onnx`` file; its metadata is
        missing, not JSON, not an object, lacks positive integer ``k``,
        ``input_points`` and ``output_points``, has bad anchor settings or frame, or
        disagrees with the network in the file (`model_check.check_against_network`:
        input and output names, anchors, points; read from the file, without onnxruntime).
    """
    path = Path(path)
    if path.is_dir():
        raise ModelError(f"model path {path} is a folder; give the model's .onnx file")
    if not path.is_file():
        raise ModelError(f"model file {path} does not exist")
    if path.suffix.lower() != ".onnx":
        raise ModelError(f"model file {path} is not an ONNX model (expected a .onnx file with its .json beside it)")
    if path.stat().st_size == 0:
        raise ModelError(f"model file {path} is empty")
    meta_path = path.with_suffix(".json")
    if not meta_path.is_file():
        raise ModelError(f"model metadata {meta_path} is missing (export-onnx writes it beside the model)")
    try:
        meta = json.loads(meta_path.read_bytes())
    except OSError as err:
        raise ModelError(f"model metadata {meta_path} cannot be read: {err.strerror or err}") from None
    except ValueError as err:  # JSONDecodeError, UnicodeDecodeError
        raise ModelError(f"model metadata {meta_path} is corrupt (not JSON: {err})") from None
    if not isinstance(meta, dict):
        raise ModelError(f"model metadata {meta_path} is corrupt (a JSON object expected, got {type(meta).__name__})")
    missing = [key for key in ("k", "input_points", "output_points") if key not in meta]
    if missing:
        raise ModelError(f"model metadata {meta_path} lacks {', '.join(missing)}")
    for key in ("k", "input_points", "output_points"):
        value = meta[key]
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ModelError(f"model metadata {meta_path}: {key} must be a positive integer, got {value!r}")
    check_against_network(meta, _signature(path), meta_path)
    _check_records(meta, meta_path)
    return meta


def _check_records(meta: dict, meta_path: Path) -> None:
    """The metadata's names, anchor settings and frame, each well formed and agreeing with the counts."""
    where = f"model metadata {meta_path}"
    for key in ("input_name", "output_name"):
        if key in meta and (not isinstance(meta[key], str) or not meta[key]):
            raise ModelError(f"{where}: {key} must be a tensor name, got {meta[key]!r}")
    anchors = meta.get("anchors") or {}
    if not isinstance(anchors, dict):
        raise ModelError(f"{where}: anchors must be a record of k, method, radius and knn, got {anchors!r}")
    if anchors.get("k", meta["k"]) != meta["k"]:
        raise ModelError(f"{where}: anchors.k is {anchors['k']!r}, but k is {meta['k']}")
    try:
        AnchorSettings.from_dict({**anchors, "k": meta["k"]})
    except (EscapeError, TypeError) as err:
        raise ModelError(f"{where}: bad anchor settings: {err}") from None
    frame = meta.get("frame")
    if frame is None or (isinstance(frame, dict) and frame.get("kind") == "absolute"):
        return  # a model trained in absolute PCN units
    if not isinstance(frame, dict) or frame.get("kind") != "partial":
        raise ModelError(f"{where}: frame must be absolute or a partial-frame record (kind, rows, radius), got {frame!r}")
    try:
        from escape_cli.core.normalize import PartialFrame

        PartialFrame(frame["rows"], frame["radius"])
    except (KeyError, TypeError, EscapeError) as err:
        raise ModelError(f"{where}: bad frame record {frame} ({err})") from None


_SIGNATURES: dict = {}  # (path, size, mtime) -> the graph's Signature (or None)


def _signature(path: Path):
    """The inputs and outputs of the ONNX graph in `path`, read once per version of the file."""
    stat = path.stat()
    key = (str(path), stat.st_size, stat.st_mtime_ns)
    if key not in _SIGNATURES:
        _SIGNATURES[key] = read_signature(path)
    return _SIGNATURES[key]


def max_output_points(meta: dict) -> int:
    """The most points a completion by this model can hold: its predicted points plus the
    observed ones merged into them (at most the network's input size)."""
    return int(meta["output_points"]) + int(meta["input_points"])


def check_output_points(points: int, meta: dict, model_name: str, name: str = "output_points") -> int:
    """`points` if the model can produce that many distinct points, else ParameterError saying why."""
    from escape_cli.core.params import as_count
    from escape_cli.errors import ParameterError

    points = as_count(points, name, minimum=1)
    ceiling = max_output_points(meta)
    if points > ceiling:
        raise ParameterError(
            f"{name} {points} is more than {model_name} can produce: at most {ceiling} "
            f"({meta['output_points']} predicted and up to {meta['input_points']} observed points)"
        )
    return points


def quiet_onnxruntime(ort=None) -> None:
    """Silence onnxruntime's own logger (its coloured warnings, e.g. about telemetry) below errors.

    Call before creating a session: the session options' level applies only to the
    session, not to the environment's messages.
    """
    if ort is None:
        import onnxruntime as ort
    ort.set_default_logger_severity(3)


def _session(path: str, threads: int):
    """A new onnxruntime session of `path`, its checksum checked (ModelError when corrupt or refused).

    The file is read once, for the checksum and for onnxruntime; both run without the
    interpreter lock, so in a background thread they overlap the caller's imports.
    """
    data = _read_model_bytes(Path(path))
    import onnxruntime as ort

    quiet_onnxruntime(ort)
    options = ort.SessionOptions()
    options.log_severity_level = 3
    if threads:
        options.intra_op_num_threads = threads
    if not SPINNING:
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
    except Exception as err:
        raise ModelError(f"cannot load model {path}: {str(err).splitlines()[0]}") from None


def _read_model_bytes(path: Path) -> bytes:
    """The model file's bytes, checked against the sha256 its metadata records (if any)."""
    try:
        data = path.read_bytes()
    except OSError as err:
        raise ModelError(f"model file {path} cannot be read: {err.strerror or err}") from None
    try:  # read_metadata reports a missing or broken .json; here it only supplies the checksum
        want = json.loads(path.with_suffix(".json").read_bytes()).get("sha256")
    except (OSError, ValueError, AttributeError):
        want = None
    if want and hashlib.sha256(data).hexdigest() != want:
        raise ModelError(f"{path} is corrupt: its checksum does not match {path.with_suffix('.json').name}")
    return data


def load_model(path: str | None = None, threads: int = 0) -> CompletionModel:
    """Load (and cache) a model: a model file, a packaged model's name (``"synth"``), or None for the default.

    Returns once the metadata is checked and the session is built, or, when a load is
    under way (`preload_model`), joins it: it is then waited for when first used
    (`CompletionModel.session`), and a corrupt file is reported there; a load under way
    is joined, not repeated. Failed loads are not cached.
    """
    resolved = model_path(path or None)
    key = (str(resolved), threads)
    with _MODELS_LOCK:
        model = _MODELS.get(key)
        if model is not None and model.failed:  # a background load that failed: try again
            del _MODELS[key]
            model = None
    if model is None:
        model = CompletionModel(resolved, threads)
        with _MODELS_LOCK:
            model = _MODELS.setdefault(key, model)
    return model


def preload_model(path: str | None = None, threads: int = 0) -> Future:
    """Start building the session of `load_model(path, threads)` in a background thread; return at once.

    onnxruntime is imported here (with numpy); the file is read and checked and the
    session built without holding the interpreter lock, so a command that knows it
    will need the model can import the rest and read and prepare its input meanwhile;
    `load_model` with the same arguments joins this load. Wait for the returned future
    before the process exits. Errors (a missing model, a file
    onnxruntime refuses) are left in the future: `load_model` reports them.
    """
    try:
        resolved = model_path(path or None)
    except EscapeError as err:
        failed: Future = Future()
        failed.set_exception(err)
        return failed
    return _session_loading(str(resolved), threads, background=True)


_MODELS: dict = {}  # (path, threads) -> CompletionModel
_SESSIONS: dict = {}  # (path, threads) -> Future of an onnxruntime session
_MODELS_LOCK = threading.Lock()


def _session_loading(path: str, threads: int, background: bool) -> Future:
    """The (cached) future session of `path`: built here, or in a new thread when `background`."""
    key = (path, threads)
    with _MODELS_LOCK:
        future = _SESSIONS.get(key)
        if future is not None:
            return future
        future = _SESSIONS[key] = Future()

    def build() -> None:
        try:
            future.set_result(_session(path, threads))
        except BaseException as err:  # handed to whoever waits; not cached
            with _MODELS_LOCK:
                _SESSIONS.pop(key, None)
            future.set_exception(err)

    if background:
        # Imported here, not in the thread: numpy's import (which onnxruntime's brings in) fails
        # when another thread imports numpy at the same time.
        import onnxruntime  # noqa: F401

        threading.Thread(target=build, name="escape-model-load", daemon=True).start()
    else:
        build()
    return future
