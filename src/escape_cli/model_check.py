"""A model checked against its metadata before any scan is read, without onnxruntime.

`read_signature` reads the names and shapes of an ONNX graph's inputs and outputs
straight from the file's protobuf encoding (seeking past the weights, so it reads a few
kilobytes of a model of any size); `check_against_network` compares them with the
metadata beside the model: the input and output names, the anchor count K (the last
axis of both), the network's input points N and its predicted points M. A mismatch is
one `ModelError` naming the field. A file that does not parse as ONNX is left to
onnxruntime, which reports it when the session is built.

ONNX fields read (onnx.proto): ModelProto.graph = 7; GraphProto.input = 11,
.output = 12; ValueInfoProto.name = 1, .type = 2; TypeProto.tensor_type = 1;
TypeProto.Tensor.shape = 2; TensorShapeProto.dim = 1; Dimension.dim_value = 1,
.dim_param = 2.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from pathlib import Path

from escape_cli.errors import ModelError

MODEL_GRAPH, GRAPH_INPUT, GRAPH_OUTPUT = 7, 11, 12
VARINT, FIXED64, BYTES, FIXED32 = 0, 1, 2, 5
MAX_VALUE_INFO_BYTES = 1 << 20  # a name and a shape: far less


@dataclass(frozen=True)
class Tensor:
    """One input or output of a graph: its name and its dimensions (int, or the name of a free axis)."""

    name: str
    dims: tuple

    def shown(self) -> str:
        return "(" + ", ".join(str(d) if isinstance(d, int) else "B" for d in self.dims) + ")"


@dataclass(frozen=True)
class Signature:
    inputs: tuple[Tensor, ...]
    outputs: tuple[Tensor, ...]


class _NotOnnx(Exception):
    """The bytes are not the protobuf encoding of an ONNX model."""


def read_signature(path: str | Path) -> Signature | None:
    """The inputs and outputs of the ONNX model in `path`; None when it does not parse as one."""
    try:
        with open(path, "rb") as handle:
            size = handle.seek(0, io.SEEK_END)
            handle.seek(0)
            graph = _find_field(handle, size, MODEL_GRAPH)
            if graph is None:
                return None
            start, length = graph
            inputs, outputs = [], []
            end = start + length
            handle.seek(start)
            while handle.tell() < end:
                field, wire = _tag(handle)
                if wire == BYTES and field in (GRAPH_INPUT, GRAPH_OUTPUT):
                    size_of = _varint(handle)
                    if size_of > MAX_VALUE_INFO_BYTES or handle.tell() + size_of > end:
                        raise _NotOnnx
                    tensor = _value_info(handle.read(size_of))
                    (inputs if field == GRAPH_INPUT else outputs).append(tensor)
                else:
                    _skip(handle, wire, end)
            return Signature(tuple(inputs), tuple(outputs))
    except (OSError, _NotOnnx, UnicodeDecodeError):
        return None


def check_against_network(meta: dict, signature: Signature | None, meta_path: Path) -> None:
    """ModelError naming the first field of the metadata `meta` the network disagrees with.

    The network takes (B, input_points, k) distances under `input_name` and gives
    (B, output_points, k) under `output_name`; axes the graph leaves free are not checked.
    """
    if signature is None:
        return
    where = f"model metadata {meta_path}"
    source = _named(signature.inputs, meta.get("input_name", "partial_distances"), "input", where)
    target = _named(signature.outputs, meta.get("output_name", "distances"), "output", where)
    for tensor, kind in ((source, "input"), (target, "output")):
        if len(tensor.dims) != 3:
            raise ModelError(f"{where}: the network's {kind} {tensor.name} is {tensor.shown()}, not (B, points, anchors)")
    for key, tensor, axis in (("k", source, 2), ("k", target, 2), ("input_points", source, 1), ("output_points", target, 1)):
        found = tensor.dims[axis]
        if isinstance(found, int) and found != meta[key]:
            kind = "input" if tensor is source else "output"
            raise ModelError(f"{where}: {key} is {meta[key]}, but the network's {kind} {tensor.name} is {tensor.shown()}")


def _named(tensors: tuple[Tensor, ...], name, kind: str, where: str) -> Tensor:
    for tensor in tensors:
        if tensor.name == name:
            return tensor
    known = ", ".join(t.name for t in tensors) or "none"
    raise ModelError(f"{where}: {kind}_name is {name!r}, but the network's {kind}s are {known}")


def _find_field(handle, end: int, wanted: int) -> tuple[int, int] | None:
    """(offset, length) of the first length-delimited field `wanted` of the message ending at `end`."""
    while handle.tell() < end:
        field, wire = _tag(handle)
        if wire == BYTES and field == wanted:
            length = _varint(handle)
            if handle.tell() + length > end:
                raise _NotOnnx
            return handle.tell(), length
        _skip(handle, wire, end)
    return None


def _value_info(data: bytes) -> Tensor:
    """A ValueInfoProto: its name and, for a tensor, its dimensions."""
    stream = io.BytesIO(data)
    name, dims = "", ()
    for field, value in _fields(stream, len(data)):
        if field == 1:
            name = value.decode("utf-8")
        elif field == 2:
            dims = _tensor_dims(value)
    return Tensor(name, dims)


def _tensor_dims(type_proto: bytes) -> tuple:
    for field, tensor in _fields(io.BytesIO(type_proto), len(type_proto)):
        if field != 1:
            continue
        for sub, shape in _fields(io.BytesIO(tensor), len(tensor)):
            if sub != 2:
                continue
            dims = []
            for dim_field, dim in _fields(io.BytesIO(shape), len(shape)):
                if dim_field == 1:
                    dims.append(_dimension(dim))
            return tuple(dims)
    return ()


def _dimension(data: bytes):
    stream = io.BytesIO(data)
    value = "?"
    while stream.tell() < len(data):
        field, wire = _tag(stream)
        if field == 1 and wire == VARINT:
            value = _varint(stream)
        elif field == 2 and wire == BYTES:
            value = stream.read(_varint(stream)).decode("utf-8") or "?"
        else:
            _skip(stream, wire, len(data))
    return value


def _fields(stream, end: int):
    """(field, bytes) of each length-delimited field of a message (others skipped)."""
    while stream.tell() < end:
        field, wire = _tag(stream)
        if wire == BYTES:
            length = _varint(stream)
            if stream.tell() + length > end:
                raise _NotOnnx
            yield field, stream.read(length)
        else:
            _skip(stream, wire, end)


def _tag(stream) -> tuple[int, int]:
    key = _varint(stream)
    field, wire = key >> 3, key & 7
    if field == 0 or wire not in (VARINT, FIXED64, BYTES, FIXED32):
        raise _NotOnnx
    return field, wire


def _varint(stream) -> int:
    value = shift = 0
    while True:
        byte = stream.read(1)
        if not byte or shift > 63:
            raise _NotOnnx
        value |= (byte[0] & 0x7F) << shift
        if byte[0] < 0x80:
            return value
        shift += 7


def _skip(stream, wire: int, end: int) -> None:
    if wire == VARINT:
        _varint(stream)
        return
    length = {FIXED64: 8, FIXED32: 4}.get(wire)
    if length is None:
        length = _varint(stream)
    if stream.tell() + length > end:
        raise _NotOnnx
    stream.seek(length, io.SEEK_CUR)
