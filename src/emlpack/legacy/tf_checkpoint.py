"""Read TensorFlow checkpoints ("tensor bundles") without TensorFlow.

A checkpoint with prefix ``P`` consists of

* ``P.index``: an SSTable in the LevelDB table format (the format described in LevelDB's
  ``doc/table_format.md``; TensorFlow keeps a copy in ``tsl/lib/io/table*``). Data blocks
  hold prefix-compressed keys with restart points; each block is followed by a 5-byte trailer
  (compression type, masked crc32c); the 48-byte footer holds the metaindex and index
  ``BlockHandle`` s (two varint64 each), zero padding and the magic ``0xdb4775248b80fb57``.
  Blocks may be uncompressed (type 0) or snappy-compressed (type 1); both are handled.
* The empty key maps to a ``BundleHeaderProto`` and every other key to a ``BundleEntryProto``
  (``tensorflow/core/protobuf/tensor_bundle.proto``): header fields ``num_shards`` = 1,
  ``endianness`` = 2, ``version`` = 3; entry fields ``dtype`` = 1, ``shape`` = 2
  (``TensorShapeProto``: ``dim`` = 2 with ``size`` = 1; ``unknown_rank`` = 3), ``shard_id`` = 3,
  ``offset`` = 4, ``size`` = 5, ``crc32c`` = 6 (fixed32, masked), ``slices`` = 7.
  These protobufs are decoded here with a minimal wire-format parser.
* ``P.data-0000k-of-0000n``: the raw tensor bytes, read at ``offset``/``size``.

Object-based checkpoints (``tf.train.Checkpoint``) name variables by object path plus
``/.ATTRIBUTES/VARIABLE_VALUE``; :func:`read_tf_checkpoint` strips that suffix. The eMLP
reference also writes ``P.pickle``, a plain dict of constructor numbers, which
:func:`read_reference_hparams` loads with a restricted unpickler.
"""

from __future__ import annotations

import pickle
import re
import struct
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from emlpack.errors import EmlpackError

__all__ = [
    "VARIABLE_SUFFIX",
    "BundleEntry",
    "BundleHeader",
    "ChecksumError",
    "MissingCheckpointFileError",
    "TFCheckpointError",
    "crc32c",
    "list_tf_checkpoint",
    "masked_crc32c",
    "read_reference_hparams",
    "read_tensor_bundle",
    "read_tf_checkpoint",
    "snappy_decompress",
]

VARIABLE_SUFFIX = "/.ATTRIBUTES/VARIABLE_VALUE"
TABLE_MAGIC = 0xDB4775248B80FB57
FOOTER_SIZE = 48  # 2 * BlockHandle.kMaxEncodedLength (20) + 8-byte magic
BLOCK_TRAILER_SIZE = 5  # 1-byte compression type + 4-byte masked crc32c

# DataType enum (tensorflow/core/framework/types.proto) -> numpy dtype (little-endian).
_NUMPY_DTYPES: dict[int, str] = {
    1: "<f4",  # DT_FLOAT
    2: "<f8",  # DT_DOUBLE
    3: "<i4",  # DT_INT32
    4: "<u1",  # DT_UINT8
    5: "<i2",  # DT_INT16
    6: "<i1",  # DT_INT8
    8: "<c8",  # DT_COMPLEX64
    9: "<i8",  # DT_INT64
    10: "<?",  # DT_BOOL
    17: "<u2",  # DT_UINT16
    18: "<c16",  # DT_COMPLEX128
    19: "<f2",  # DT_HALF
    22: "<u4",  # DT_UINT32
    23: "<u8",  # DT_UINT64
}
DT_STRING = 7

# Top-level checkpoint objects that are bookkeeping, not model variables.
_NON_MODEL_ROOTS = ("save_counter", "optimizer", "_CHECKPOINTABLE_OBJECT_GRAPH")


class TFCheckpointError(EmlpackError):
    """A file is not a readable TensorFlow checkpoint (the message names the file)."""


class MissingCheckpointFileError(TFCheckpointError, FileNotFoundError):
    """The ``.index``, a ``.data-*`` shard or the ``.pickle`` of a checkpoint is missing."""


class ChecksumError(TFCheckpointError):
    """A stored crc32c does not match the bytes read."""


# --------------------------------------------------------------------------------------------
# crc32c (Castagnoli, reflected polynomial 0x82F63B78)


def _make_crc_table() -> list[int]:
    table = []
    for n in range(256):
        c = n
        for _ in range(8):
            c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
        table.append(c)
    return table


_CRC_TABLE = _make_crc_table()
_CRC_TABLE_NP = np.array(_CRC_TABLE, dtype=np.uint32)
_CHUNK = 1024  # lane length of the vectorised crc
_zero_shift_tables: list[list[int]] | None = None


def _crc_update(state: int, data: bytes | memoryview) -> int:
    """Raw (unconditioned) crc32c register update, one byte at a time."""
    table = _CRC_TABLE
    for b in bytes(data):
        state = table[(state ^ b) & 0xFF] ^ (state >> 8)
    return state


def _zero_shift() -> list[list[int]]:
    """Byte tables of the linear map 'feed _CHUNK zero bytes' on the crc register."""
    global _zero_shift_tables
    if _zero_shift_tables is None:
        zeros = bytes(_CHUNK)
        columns = [_crc_update(1 << bit, zeros) for bit in range(32)]
        tables = []
        for k in range(4):
            t = [0] * 256
            for b in range(1, 256):
                low = (b & -b).bit_length() - 1
                t[b] = t[b & (b - 1)] ^ columns[8 * k + low]
            tables.append(t)
        _zero_shift_tables = tables
    return _zero_shift_tables


def _crc_update_numpy(state: int, data: bytes | memoryview) -> int:
    """Raw crc32c update: all _CHUNK-byte chunks in parallel lanes, then a GF(2) fold."""
    n_chunks = len(data) // _CHUNK
    body = np.frombuffer(data, dtype=np.uint8, count=n_chunks * _CHUNK)
    columns = np.ascontiguousarray(body.reshape(n_chunks, _CHUNK).T)
    lanes = np.zeros(n_chunks, dtype=np.uint32)
    lanes[0] = state
    table = _CRC_TABLE_NP
    for column in columns:
        lanes = table[(lanes ^ column) & 0xFF] ^ (lanes >> 8)
    t0, t1, t2, t3 = _zero_shift()
    state = 0
    for lane in lanes.tolist():
        state = (
            t0[state & 0xFF] ^ t1[(state >> 8) & 0xFF] ^ t2[(state >> 16) & 0xFF] ^ t3[state >> 24]
        ) ^ lane
    return _crc_update(state, memoryview(data)[n_chunks * _CHUNK :])


def crc32c(data: bytes | bytearray | memoryview, *, vectorized: bool | None = None) -> int:
    """CRC-32C of ``data``; large inputs use a numpy lane-parallel kernel."""
    if vectorized is None:
        vectorized = len(data) >= 64 * _CHUNK
    update = _crc_update_numpy if vectorized and len(data) >= _CHUNK else _crc_update
    return update(0xFFFFFFFF, data) ^ 0xFFFFFFFF


def masked_crc32c(data: bytes | bytearray | memoryview) -> int:
    """The masked crc32c stored by LevelDB and TensorFlow: rotate right by 15, add a constant."""
    crc = crc32c(data)
    return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


# --------------------------------------------------------------------------------------------
# varints, protobuf wire format, snappy


def _varint(buf: bytes | memoryview, pos: int, where: str) -> tuple[int, int]:
    """Decode a base-128 varint at ``pos``; return (value, new position)."""
    result = 0
    shift = 0
    while True:
        if pos >= len(buf):
            raise TFCheckpointError(f"{where}: truncated varint")
        b = buf[pos]
        pos += 1
        result |= (b & 0x7F) << shift
        if not b & 0x80:
            return result, pos
        shift += 7
        if shift >= 64:
            raise TFCheckpointError(f"{where}: varint longer than 10 bytes")


def _signed64(value: int) -> int:
    return value - (1 << 64) if value >= 1 << 63 else value


def _proto_fields(buf: bytes, where: str) -> list[tuple[int, int, int | bytes]]:
    """Parse a protobuf message into (field number, wire type, int or bytes) triples."""
    fields: list[tuple[int, int, int | bytes]] = []
    pos = 0
    while pos < len(buf):
        tag, pos = _varint(buf, pos, where)
        number, wire = tag >> 3, tag & 7
        value: int | bytes
        if wire == 0:
            value, pos = _varint(buf, pos, where)
        elif wire == 1:
            if pos + 8 > len(buf):
                raise TFCheckpointError(f"{where}: truncated fixed64 field {number}")
            (value,) = struct.unpack_from("<Q", buf, pos)
            pos += 8
        elif wire == 2:
            length, pos = _varint(buf, pos, where)
            if pos + length > len(buf):
                raise TFCheckpointError(f"{where}: truncated length-delimited field {number}")
            value = bytes(buf[pos : pos + length])
            pos += length
        elif wire == 5:
            if pos + 4 > len(buf):
                raise TFCheckpointError(f"{where}: truncated fixed32 field {number}")
            (value,) = struct.unpack_from("<I", buf, pos)
            pos += 4
        else:
            raise TFCheckpointError(f"{where}: unsupported protobuf wire type {wire}")
        if number == 0:
            raise TFCheckpointError(f"{where}: invalid protobuf field number 0")
        fields.append((number, wire, value))
    return fields


def snappy_decompress(data: bytes, where: str = "snappy block") -> bytes:
    """Decompress one raw snappy block (google/snappy ``format_description.txt``)."""
    length, pos = _varint(data, 0, where)
    out = bytearray()
    while pos < len(data):
        tag = data[pos]
        pos += 1
        kind = tag & 3
        if kind == 0:  # literal
            n = tag >> 2
            if n >= 60:
                extra = n - 59
                n = int.from_bytes(data[pos : pos + extra], "little")
                pos += extra
            n += 1
            if pos + n > len(data):
                raise TFCheckpointError(f"{where}: truncated snappy literal")
            out += data[pos : pos + n]
            pos += n
            continue
        if kind == 1:
            n = 4 + ((tag >> 2) & 7)
            offset = ((tag >> 5) << 8) | data[pos]
            pos += 1
        else:
            n = 1 + (tag >> 2)
            width = 2 if kind == 2 else 4
            offset = int.from_bytes(data[pos : pos + width], "little")
            pos += width
        if pos > len(data) or offset == 0 or offset > len(out):
            raise TFCheckpointError(f"{where}: corrupt snappy copy")
        start = len(out) - offset
        if offset >= n:
            out += out[start : start + n]
        else:  # overlapping copy repeats the last `offset` bytes
            for i in range(n):
                out.append(out[start + i])
    if len(out) != length:
        raise TFCheckpointError(f"{where}: snappy length {len(out)} != declared {length}")
    return bytes(out)


# --------------------------------------------------------------------------------------------
# LevelDB table (the .index file)


def _read_block(buf: bytes, handle: tuple[int, int], where: str) -> bytes:
    """Contents of the block at (offset, size), checksum-verified and decompressed."""
    offset, size = handle
    end = offset + size + BLOCK_TRAILER_SIZE
    if end > len(buf) - FOOTER_SIZE:
        raise TFCheckpointError(
            f"{where}: block at {offset}+{size} runs past the data (truncated?)"
        )
    contents = buf[offset : offset + size]
    kind = buf[offset + size]
    (stored,) = struct.unpack_from("<I", buf, offset + size + 1)
    if masked_crc32c(buf[offset : offset + size + 1]) != stored:
        raise ChecksumError(f"{where}: block checksum mismatch at offset {offset}")
    if kind == 0:
        return contents
    if kind == 1:
        return snappy_decompress(contents, where)
    raise TFCheckpointError(f"{where}: unsupported block compression type {kind}")


def _block_entries(block: bytes, where: str) -> list[tuple[bytes, bytes]]:
    """Key/value pairs of one block, undoing the prefix compression of keys."""
    if len(block) < 4:
        raise TFCheckpointError(f"{where}: block too short")
    (n_restarts,) = struct.unpack_from("<I", block, len(block) - 4)
    limit = len(block) - 4 - 4 * n_restarts
    if limit < 0:
        raise TFCheckpointError(f"{where}: bad restart count {n_restarts}")
    entries: list[tuple[bytes, bytes]] = []
    key = b""
    pos = 0
    while pos < limit:
        shared, pos = _varint(block, pos, where)
        unshared, pos = _varint(block, pos, where)
        value_len, pos = _varint(block, pos, where)
        if shared > len(key) or pos + unshared + value_len > limit:
            raise TFCheckpointError(f"{where}: corrupt block entry")
        key = key[:shared] + block[pos : pos + unshared]
        pos += unshared
        entries.append((key, block[pos : pos + value_len]))
        pos += value_len
    return entries


def _block_handle(value: bytes, where: str) -> tuple[int, int]:
    offset, pos = _varint(value, 0, where)
    size, _ = _varint(value, pos, where)
    return offset, size


def _read_table(path: Path) -> list[tuple[bytes, bytes]]:
    """All key/value pairs of a LevelDB-format SSTable, in file order."""
    where = str(path)
    buf = path.read_bytes()
    if len(buf) < FOOTER_SIZE:
        raise TFCheckpointError(f"{where}: {len(buf)} bytes, too short for a table (truncated?)")
    footer = buf[-FOOTER_SIZE:]
    (magic,) = struct.unpack_from("<Q", footer, FOOTER_SIZE - 8)
    if magic != TABLE_MAGIC:
        raise TFCheckpointError(
            f"{where}: bad table magic {magic:#018x} (expected {TABLE_MAGIC:#018x}); "
            "not a TensorFlow checkpoint index, or truncated"
        )
    _, pos = _varint(footer, 0, where)  # metaindex offset
    _, pos = _varint(footer, pos, where)  # metaindex size (no meta blocks are needed)
    index_offset, pos = _varint(footer, pos, where)
    index_size, pos = _varint(footer, pos, where)
    index = _block_entries(_read_block(buf, (index_offset, index_size), where), where)
    entries: list[tuple[bytes, bytes]] = []
    for _, handle in index:
        block = _read_block(buf, _block_handle(handle, where), where)
        entries.extend(_block_entries(block, where))
    return entries


# --------------------------------------------------------------------------------------------
# tensor bundle


@dataclass(frozen=True)
class BundleHeader:
    """``BundleHeaderProto``: shard count, endianness (0 little, 1 big), producer version."""

    num_shards: int
    endianness: int
    version_producer: int


@dataclass(frozen=True)
class BundleEntry:
    """``BundleEntryProto`` of one tensor (``shape`` is None for unknown rank)."""

    dtype: int
    shape: tuple[int, ...] | None
    shard_id: int
    offset: int
    size: int
    crc32c: int
    sliced: bool


def _parse_header(value: bytes, where: str) -> BundleHeader:
    num_shards, endianness, producer = 1, 0, 0
    for number, _, v in _proto_fields(value, where):
        if number == 1:
            num_shards = int(v)  # type: ignore[arg-type]
        elif number == 2:
            endianness = int(v)  # type: ignore[arg-type]
        elif number == 3 and isinstance(v, bytes):
            for n, _, w in _proto_fields(v, where):
                if n == 1:
                    producer = int(w)  # type: ignore[arg-type]
    return BundleHeader(num_shards, endianness, producer)


def _parse_shape(value: bytes, where: str) -> tuple[int, ...] | None:
    dims: list[int] = []
    for number, _, v in _proto_fields(value, where):
        if number == 2 and isinstance(v, bytes):
            size = 0
            for n, _, w in _proto_fields(v, where):
                if n == 1:
                    size = _signed64(int(w))  # type: ignore[arg-type]
            dims.append(size)
        elif number == 3 and v:
            return None
    return tuple(dims)


def _parse_entry(value: bytes, where: str) -> BundleEntry:
    dtype, shard_id, offset, size, crc, sliced = 0, 0, 0, 0, 0, False
    shape: tuple[int, ...] | None = ()
    for number, _, v in _proto_fields(value, where):
        if number == 1:
            dtype = int(v)  # type: ignore[arg-type]
        elif number == 2 and isinstance(v, bytes):
            shape = _parse_shape(v, where)
        elif number == 3:
            shard_id = int(v)  # type: ignore[arg-type]
        elif number == 4:
            offset = _signed64(int(v))  # type: ignore[arg-type]
        elif number == 5:
            size = _signed64(int(v))  # type: ignore[arg-type]
        elif number == 6:
            crc = int(v)  # type: ignore[arg-type]
        elif number == 7:
            sliced = True
    return BundleEntry(dtype, shape, shard_id, offset, size, crc, sliced)


def _prefix_path(prefix: str | Path) -> Path:
    """Accept ``P``, ``P.index``, ``P.pickle`` or ``P.data-*-of-*`` and return ``P``."""
    path = Path(prefix)
    name = re.sub(r"\.(index|pickle|data-\d{5}-of-\d{5})$", "", path.name)
    return path.with_name(name)


def _index_path(prefix: str | Path) -> Path:
    path = _prefix_path(prefix).with_name(_prefix_path(prefix).name + ".index")
    if not path.is_file():
        raise MissingCheckpointFileError(f"{path}: checkpoint index not found")
    return path


def list_tf_checkpoint(prefix: str | Path) -> tuple[BundleHeader, dict[str, BundleEntry]]:
    """Header and entries of ``PREFIX.index`` under their raw checkpoint keys."""
    path = _index_path(prefix)
    where = str(path)
    header: BundleHeader | None = None
    entries: dict[str, BundleEntry] = {}
    for key, value in _read_table(path):
        if key == b"":
            header = _parse_header(value, where)
            continue
        try:
            name = key.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise TFCheckpointError(f"{where}: key {key!r} is not UTF-8") from exc
        entries[name] = _parse_entry(value, f"{where} [{name}]")
    if header is None:
        raise TFCheckpointError(f"{where}: no bundle header (empty key); not a tensor bundle")
    if header.num_shards < 1:
        raise TFCheckpointError(f"{where}: invalid num_shards {header.num_shards}")
    if header.endianness not in (0, 1):
        raise TFCheckpointError(f"{where}: invalid endianness {header.endianness}")
    return header, entries


def read_tensor_bundle(
    prefix: str | Path, *, verify_crc: bool = True
) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Every tensor of a bundle under its raw key, plus {key: reason} for skipped entries.

    String and other non-numeric tensors (e.g. ``_CHECKPOINTABLE_OBJECT_GRAPH``) and sliced
    (partitioned) variables are skipped, not decoded.
    """
    base = _prefix_path(prefix)
    header, entries = list_tf_checkpoint(base)
    order = ">" if header.endianness == 1 else "<"
    shards: dict[int, bytes] = {}
    tensors: dict[str, np.ndarray] = {}
    skipped: dict[str, str] = {}
    for key, entry in entries.items():
        if entry.sliced:
            skipped[key] = "sliced (partitioned) variable"
            continue
        if entry.dtype not in _NUMPY_DTYPES:
            skipped[key] = "string" if entry.dtype == DT_STRING else f"dtype enum {entry.dtype}"
            continue
        if entry.shape is None or any(d < 0 for d in entry.shape):
            raise TFCheckpointError(f"{base}.index: {key} has an unknown shape {entry.shape}")
        if not 0 <= entry.shard_id < header.num_shards:
            raise TFCheckpointError(f"{base}.index: {key} has invalid shard_id {entry.shard_id}")
        shard_path = base.with_name(
            f"{base.name}.data-{entry.shard_id:05d}-of-{header.num_shards:05d}"
        )
        if entry.shard_id not in shards:
            if not shard_path.is_file():
                raise MissingCheckpointFileError(f"{shard_path}: checkpoint data shard not found")
            shards[entry.shard_id] = shard_path.read_bytes()
        data = shards[entry.shard_id]
        dtype = np.dtype(_NUMPY_DTYPES[entry.dtype]).newbyteorder(order)
        count = int(np.prod(entry.shape, dtype=np.int64))
        if entry.size != count * dtype.itemsize:
            raise TFCheckpointError(
                f"{base}.index: {key} size {entry.size} does not match shape {entry.shape} "
                f"of {dtype} ({count * dtype.itemsize} bytes)"
            )
        if entry.offset < 0 or entry.offset + entry.size > len(data):
            raise TFCheckpointError(
                f"{shard_path}: {key} needs bytes {entry.offset}..{entry.offset + entry.size} "
                f"but the file has {len(data)} (truncated?)"
            )
        raw = memoryview(data)[entry.offset : entry.offset + entry.size]
        if verify_crc and masked_crc32c(raw) != entry.crc32c:
            raise ChecksumError(f"{shard_path}: crc32c mismatch for {key} (corrupted data)")
        array = np.frombuffer(raw, dtype=dtype, count=count).reshape(entry.shape)
        tensors[key] = array.astype(dtype.newbyteorder("="), copy=True)
    return tensors, skipped


def _is_model_variable(key: str) -> bool:
    return (
        key.endswith(VARIABLE_SUFFIX)
        and "/.OPTIMIZER_SLOT/" not in key
        and key.split("/", 1)[0] not in _NON_MODEL_ROOTS
    )


def read_tf_checkpoint(prefix: str | Path, *, verify_crc: bool = True) -> dict[str, np.ndarray]:
    """Model variables of a ``tf.train.Checkpoint``, keyed by object path without the suffix.

    Bookkeeping entries (``_CHECKPOINTABLE_OBJECT_GRAPH``, ``save_counter``, optimizer state)
    are dropped; use :func:`read_tensor_bundle` to see everything.
    """
    base = _prefix_path(prefix)
    _, entries = list_tf_checkpoint(base)
    for key, entry in entries.items():
        if _is_model_variable(key) and (entry.sliced or entry.dtype not in _NUMPY_DTYPES):
            why = "sliced" if entry.sliced else f"dtype enum {entry.dtype}"
            raise TFCheckpointError(f"{base}.index: variable {key} is {why}, not supported")
    tensors, _ = read_tensor_bundle(base, verify_crc=verify_crc)
    return {
        key[: -len(VARIABLE_SUFFIX)]: value
        for key, value in sorted(tensors.items())
        if _is_model_variable(key)
    }


# --------------------------------------------------------------------------------------------
# reference hyperparameters (.pickle)

_SAFE_GLOBALS = {
    ("builtins", "set"),
    ("builtins", "frozenset"),
    ("builtins", "complex"),
    ("builtins", "bytearray"),
    ("collections", "OrderedDict"),
    ("numpy", "dtype"),
    ("numpy", "ndarray"),
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy._core.multiarray", "_reconstruct"),
    ("numpy._core.multiarray", "scalar"),
}


class _RestrictedUnpickler(pickle.Unpickler):
    """Unpickler that only reconstructs plain containers, numbers, strings and numpy values."""

    def __init__(self, file: BinaryIO, where: str) -> None:
        super().__init__(file)
        self._where = where

    def find_class(self, module: str, name: str):
        if (module, name) in _SAFE_GLOBALS:
            return super().find_class(module, name)
        raise TFCheckpointError(
            f"{self._where}: refusing to unpickle {module}.{name}; only plain dicts, lists, "
            "numbers, strings and numpy values are allowed"
        )


def read_reference_hparams(prefix: str | Path) -> dict:
    """The eMLP reference's hyperparameter dict from ``PREFIX.pickle``, loaded safely."""
    path = _prefix_path(prefix)
    path = path.with_name(path.name + ".pickle")
    if not path.is_file():
        raise MissingCheckpointFileError(f"{path}: reference hyperparameter pickle not found")
    with path.open("rb") as f:
        try:
            value = _RestrictedUnpickler(f, str(path)).load()
        except TFCheckpointError:
            raise
        except Exception as exc:  # truncated or garbage pickle
            raise TFCheckpointError(f"{path}: not a readable pickle ({exc})") from exc
    if not isinstance(value, dict):
        raise TFCheckpointError(f"{path}: expected a dict, got {type(value).__name__}")
    return value
