"""LZF decompression (Marc Lehmann's liblzf format), as PCD's `binary_compressed` data uses it.

`lzf_decompress` uses liblzf's own C decoder when the optional package `python-lzf` is installed
(`pip install python-lzf`: a C extension, built from source, so it needs a C compiler) and the
pure-Python decoder `lzf_decompress_python` otherwise. On PCL's `office1.pcd` (4.9 MB from
1.9 MB) the C decoder takes 5 ms and the Python one 380-600 ms (Open3D reads the whole file in
106 ms); a NumPy decoder (chunk starts found by walking 512-byte segments in lockstep, literals
scattered, back references resolved by pointer jumping) was 2x slower than the Python loop, so
there is none. The Python decoder also reports where a corrupt stream fails: the C decoder's
errors are re-run through it.
"""

from ._common import byte_error

try:  # the optional accelerator; see the module docstring
    from lzf import decompress as _c_decompress
except ImportError:
    _c_decompress = None


def lzf_decompress(data, size, path, offset) -> bytes:
    """Decompress LZF `data` to exactly `size` bytes: liblzf's C decoder from `python-lzf` when
    installed, else (and to locate the error in a corrupt stream) `lzf_decompress_python`,
    whose arguments and errors these are."""
    if _c_decompress is not None and size:
        try:
            out = _c_decompress(bytes(data), size)
        except ValueError:  # corrupt data: the Python decoder names the chunk
            out = None
        if out is not None and len(out) == size:
            return out
    return lzf_decompress_python(data, size, path, offset)


def lzf_decompress_python(data, size, path, offset) -> bytes:
    r"""Decompress LZF `data` to exactly `size` bytes, refusing a corrupt stream as liblzf's
    `lzf_decompress` does.

    The stream is a sequence of chunks, each opened by a control byte $c$: $c < 32$ is a literal
    run of the next $c + 1$ bytes; otherwise a back reference copies $L + 2$ bytes from $d$ bytes
    before the end of the output, where $L = c \gg 5$ (plus the next byte when $L = 7$) and
    $d = ((c \mathbin{\&} 31) \ll 8) + b + 1$ with $b$ the byte after (liblzf's `lzf_d.c`). A
    copy may overlap its own output, repeating its last $d$ bytes.

    **Arguments:**

    - `data`: the compressed bytes.
    - `size`: the uncompressed size the file declares.
    - `path`, `offset`: the file and the byte where `data` starts in it, for the error message.

    **Raises:** `PointCloudFileError` naming the byte of the chunk at fault for a chunk that reads
    past the end of `data`, writes past `size`, or refers before the start of the output, and for
    a stream that ends short of `size`.
    """
    out = bytearray(size)
    i = j = 0
    n = len(data)
    while i < n:
        start = i
        control = data[i]
        i += 1
        if control < 32:
            length = control + 1
            if i + length > n:
                raise byte_error(
                    path,
                    offset + start,
                    f"LZF literal run of {length} bytes goes past the end of the compressed data "
                    f"({n - i} bytes left)",
                )
            if j + length > size:
                raise _overrun(path, offset + start, j + length, size)
            out[j : j + length] = data[i : i + length]
            i += length
            j += length
            continue
        length = control >> 5
        if length == 7:
            if i >= n:
                raise _truncated(path, offset + start)
            length += data[i]
            i += 1
        if i >= n:
            raise _truncated(path, offset + start)
        distance = ((control & 0x1F) << 8) + data[i] + 1
        i += 1
        length += 2
        reference = j - distance
        if reference < 0:
            raise byte_error(
                path,
                offset + start,
                f"LZF back reference {distance} bytes back from output byte {j}, before the "
                "start of the output (corrupt data)",
            )
        if j + length > size:
            raise _overrun(path, offset + start, j + length, size)
        if distance >= length:
            out[j : j + length] = out[reference : reference + length]
        else:  # overlapping its own output: the last `distance` bytes repeated
            out[j : j + length] = (out[reference:j] * (length // distance + 1))[:length]
        j += length
    if j != size:
        raise byte_error(
            path,
            offset + n,
            f"LZF data ends after {j} uncompressed bytes, expected {size} (truncated data)",
        )
    return bytes(out)


def _overrun(path, offset, end, size):
    return byte_error(
        path,
        offset,
        f"LZF chunk writes up to byte {end}, past the declared uncompressed size {size}",
    )


def _truncated(path, offset):
    return byte_error(path, offset, "LZF back reference cut off by the end of the compressed data")
