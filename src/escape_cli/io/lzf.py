"""LZF decompression (the codec of PCD ``binary_compressed`` bodies), pure Python.

LZF is a byte-oriented LZ77 variant. The stream is a sequence of tokens, each
starting with a control byte ``ctrl``:

- ``ctrl < 32``: a literal run; the next ``ctrl + 1`` bytes are copied as they are.
- ``ctrl >= 32``: a back-reference of length ``(ctrl >> 5) + 2`` (when ``ctrl >> 5``
  is 7, one more byte is added to the length) to the output ``((ctrl & 31) << 8) +
  next_byte + 1`` bytes back. Source and destination may overlap (a run).

`lzf_decompress` copies whole slices per token and is the one to use;
`lzf_decompress_naive` copies byte by byte, is obviously correct, and exists so the
tests can check that the two agree.
"""

from __future__ import annotations


class LZFError(ValueError):
    """The compressed stream is corrupt or does not decompress to the expected size."""


def lzf_decompress(compressed: bytes, uncompressed_size: int) -> bytes:
    """Decompress an LZF stream whose decompressed size is known.

    Parameters
    ----------
    compressed : bytes
        The LZF stream.
    uncompressed_size : int
        The exact number of bytes the stream decompresses to.

    Returns
    -------
    bytes
        ``uncompressed_size`` bytes.

    Raises
    ------
    LZFError
        The stream is truncated, refers before the start of the output, or does not
        produce exactly ``uncompressed_size`` bytes.
    """
    source = memoryview(compressed)
    source_size = len(source)
    output = bytearray(uncompressed_size)
    in_pos = 0
    out_pos = 0
    try:
        while in_pos < source_size:
            ctrl = source[in_pos]
            in_pos += 1
            if ctrl < 32:  # literal run of ctrl + 1 bytes
                length = ctrl + 1
                if in_pos + length > source_size:
                    raise LZFError("literal run past the end of the compressed data")
                if out_pos + length > uncompressed_size:
                    raise LZFError("data decompresses to more bytes than announced")
                output[out_pos : out_pos + length] = source[in_pos : in_pos + length]
                in_pos += length
                out_pos += length
                continue
            length = ctrl >> 5
            if length == 7:
                length += source[in_pos]
                in_pos += 1
            length += 2
            distance = ((ctrl & 0x1F) << 8) + source[in_pos] + 1
            in_pos += 1
            ref = out_pos - distance
            if ref < 0:
                raise LZFError("back-reference before the start of the output")
            end = out_pos + length
            if end > uncompressed_size:
                raise LZFError("data decompresses to more bytes than announced")
            if distance >= length:  # no overlap: one slice copy
                output[out_pos:end] = output[ref : ref + length]
            else:  # overlapping run: repeat the last `distance` bytes
                pattern = bytes(output[ref:out_pos])
                output[out_pos:end] = (pattern * (length // distance + 1))[:length]
            out_pos = end
    except IndexError:
        raise LZFError("back-reference cut off at the end of the compressed data") from None
    if out_pos != uncompressed_size:
        raise LZFError(f"data decompresses to {out_pos} bytes, {uncompressed_size} announced")
    return bytes(output)


def lzf_decompress_naive(compressed: bytes, uncompressed_size: int) -> bytes:
    """Byte-by-byte reference version of `lzf_decompress` (slow; for tests)."""
    output = bytearray()
    in_pos = 0
    try:
        while in_pos < len(compressed):
            ctrl = compressed[in_pos]
            in_pos += 1
            if ctrl < 32:
                for _ in range(ctrl + 1):
                    output.append(compressed[in_pos])
                    in_pos += 1
            else:
                length = ctrl >> 5
                if length == 7:
                    length += compressed[in_pos]
                    in_pos += 1
                ref = len(output) - ((ctrl & 0x1F) << 8) - compressed[in_pos] - 1
                in_pos += 1
                if ref < 0:
                    raise LZFError("back-reference before the start of the output")
                for _ in range(length + 2):
                    output.append(output[ref])
                    ref += 1
    except IndexError:
        raise LZFError("stream cut off at the end of the compressed data") from None
    if len(output) != uncompressed_size:
        raise LZFError(f"data decompresses to {len(output)} bytes, {uncompressed_size} announced")
    return bytes(output)
