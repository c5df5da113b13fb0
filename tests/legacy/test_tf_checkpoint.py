"""Tests of the TensorFlow-free checkpoint reader against the reference fixtures."""

from __future__ import annotations

import json
import pickle
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest

from emlpack.legacy import tf_checkpoint as tfc
from emlpack.legacy.tf_checkpoint import (
    ChecksumError,
    MissingCheckpointFileError,
    TFCheckpointError,
    crc32c,
    list_tf_checkpoint,
    masked_crc32c,
    read_reference_hparams,
    read_tensor_bundle,
    read_tf_checkpoint,
    snappy_decompress,
)
from tests.conftest import shared_path

FIXTURES = "fixtures/reference_tf"
NAMES = ["small", "paper"]
DATA = ".data-00000-of-00001"


def _prefix(name: str) -> Path:
    return shared_path(f"{FIXTURES}/tf_checkpoint_{name}/{name}.index").with_suffix("")


def _copy(name: str, tmp_path: Path) -> Path:
    """Writable copy of a fixture checkpoint; returns its prefix."""
    src = _prefix(name)
    for suffix in (".index", DATA, ".pickle"):
        shutil.copyfile(f"{src}{suffix}", tmp_path / f"{name}{suffix}")
        (tmp_path / f"{name}{suffix}").chmod(0o644)
    return tmp_path / name


def _flip(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x5A
    path.write_bytes(bytes(data))


# ---------------------------------------------------------------------------------------------
# crc32c and snappy


def test_crc32c_known_vectors():
    assert crc32c(b"") == 0
    assert crc32c(b"123456789") == 0xE3069283
    assert crc32c(bytes(32)) == 0x8A9136AA  # RFC 3720 B.4
    assert crc32c(b"\xff" * 32) == 0x62A8AB43
    assert crc32c(bytes(range(32))) == 0x46DD794E


@pytest.mark.parametrize("n", [1023, 1024, 1025, 70_000, 3 * 1024 * 64 + 5])
def test_crc32c_vectorized_matches_bytewise(n):
    data = np.random.default_rng(n).bytes(n)
    assert crc32c(data, vectorized=True) == crc32c(data, vectorized=False)


def test_masked_crc32c_is_leveldb_mask():
    crc = crc32c(b"foo")
    assert masked_crc32c(b"foo") == ((((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF)
    assert masked_crc32c(b"foo") != crc


def test_snappy_decompress_literals_and_copies():
    # "abcd" literal, then a 2-byte-offset copy of 16 bytes at offset 4 (overlapping)
    assert snappy_decompress(b"\x14\x0cabcd\x3e\x04\x00") == b"abcd" * 5
    # 1-byte-offset copy: length 4 + 3 = 7, offset 2
    assert snappy_decompress(b"\x09\x04xy\x0d\x02") == b"xyxyxyxyx"
    # literal longer than 60 bytes (one extra length byte)
    text = bytes(range(100))
    assert snappy_decompress(bytes([100, 60 << 2, 99]) + text) == text
    with pytest.raises(TFCheckpointError, match="snappy"):
        snappy_decompress(b"\x05\x0cabcd")  # declared length 5, got 4
    with pytest.raises(TFCheckpointError, match="snappy"):
        snappy_decompress(b"\x08\x0e\x09\x00")  # copy before any output


# ---------------------------------------------------------------------------------------------
# fixture checkpoints


@pytest.mark.parametrize("name", NAMES)
def test_weights_match_npz_bitwise(name):
    weights = read_tf_checkpoint(_prefix(name))
    with np.load(shared_path(f"{FIXTURES}/weights_{name}.npz")) as ref:
        assert set(weights) == set(ref.files)
        for key in ref.files:
            expected = ref[key]
            assert weights[key].dtype == expected.dtype == np.float32, key
            assert weights[key].shape == expected.shape, key
            assert weights[key].tobytes() == expected.tobytes(), key
    assert all(array.flags.writeable for array in weights.values())


@pytest.mark.parametrize("name", NAMES)
def test_hparams_match_json(name):
    hparams = read_reference_hparams(_prefix(name))
    kwargs = json.loads(shared_path(f"{FIXTURES}/hparams_{name}.json").read_text())[
        "constructor_kwargs"
    ]
    assert set(hparams) == {
        "cutoff",
        "n_max",
        "start",
        "end",
        "shared_W_interactions",
        "cutoff_transition_width",
        "num_features",
        "num_layers",
        "num_filters",
    }
    for key, value in hparams.items():
        assert value == kwargs[key] and type(value) is type(kwargs[key]), key


def test_listing_header_and_bookkeeping_entries():
    header, entries = list_tf_checkpoint(_prefix("small"))
    assert (header.num_shards, header.endianness) == (1, 0)
    assert len(entries) == 28
    graph = entries["_CHECKPOINTABLE_OBJECT_GRAPH"]
    assert graph.dtype == tfc.DT_STRING
    init = entries["model/init_features/.ATTRIBUTES/VARIABLE_VALUE"]
    assert (init.dtype, init.shape, init.size) == (1, (100, 32), 100 * 32 * 4)
    tensors, skipped = read_tensor_bundle(_prefix("small"))
    assert skipped == {"_CHECKPOINTABLE_OBJECT_GRAPH": "string"}
    assert len(tensors) == 27


def test_prefix_may_name_any_checkpoint_file():
    prefix = _prefix("small")
    a = read_tf_checkpoint(f"{prefix}.index")
    b = read_tf_checkpoint(f"{prefix}{DATA}", verify_crc=False)
    assert a.keys() == b.keys()
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert read_reference_hparams(f"{prefix}.index")["num_features"] == 32


def test_model_variable_filter():
    assert tfc._is_model_variable("model/x/.ATTRIBUTES/VARIABLE_VALUE")
    assert not tfc._is_model_variable("save_counter/.ATTRIBUTES/VARIABLE_VALUE")
    assert not tfc._is_model_variable("optimizer/iter/.ATTRIBUTES/VARIABLE_VALUE")
    assert not tfc._is_model_variable(
        "model/x/.OPTIMIZER_SLOT/optimizer/m/.ATTRIBUTES/VARIABLE_VALUE"
    )
    assert not tfc._is_model_variable("_CHECKPOINTABLE_OBJECT_GRAPH")


# ---------------------------------------------------------------------------------------------
# re-encoded tables: several data blocks, restart points, snappy compression


def _varint(n: int) -> bytes:
    out = bytearray()
    while True:
        out.append((n & 0x7F) | (0x80 if n > 0x7F else 0))
        n >>= 7
        if not n:
            return bytes(out)


def _encode_block(entries: list[tuple[bytes, bytes]], restart_interval: int) -> bytes:
    out, restarts, last = bytearray(), [], b""
    for i, (key, value) in enumerate(entries):
        shared = 0
        if i % restart_interval == 0:
            restarts.append(len(out))
        else:
            while shared < min(len(key), len(last)) and key[shared] == last[shared]:
                shared += 1
        out += _varint(shared) + _varint(len(key) - shared) + _varint(len(value))
        out += key[shared:] + value
        last = key
    restarts = restarts or [0]
    out += b"".join(struct.pack("<I", r) for r in restarts) + struct.pack("<I", len(restarts))
    return bytes(out)


def _snappy_literals(data: bytes) -> bytes:
    out = bytearray(_varint(len(data)))
    for i in range(0, len(data), 60):
        chunk = data[i : i + 60]
        out += bytes([(len(chunk) - 1) << 2]) + chunk
    return bytes(out)


def _write_table(path: Path, entries, per_block: int, compress: bool) -> None:
    out, index = bytearray(), []

    def put(contents: bytes, kind: int) -> bytes:
        handle = _varint(len(out)) + _varint(len(contents))
        trailer = bytes([kind]) + struct.pack("<I", masked_crc32c(contents + bytes([kind])))
        out.extend(contents + trailer)
        return handle

    for i in range(0, len(entries), per_block):
        chunk = entries[i : i + per_block]
        block = _encode_block(chunk, restart_interval=3)
        handle = put(_snappy_literals(block), 1) if compress else put(block, 0)
        index.append((chunk[-1][0], handle))
    meta = put(_encode_block([], 16), 0)
    idx = put(_encode_block(index, 1), 0)
    footer = (meta + idx).ljust(40, b"\0") + struct.pack("<Q", tfc.TABLE_MAGIC)
    path.write_bytes(bytes(out) + footer)


@pytest.mark.parametrize("compress", [False, True])
def test_reencoded_index_reads_identically(tmp_path, compress):
    prefix = _copy("small", tmp_path)
    expected = read_tf_checkpoint(prefix)
    entries = tfc._read_table(Path(f"{prefix}.index"))
    _write_table(Path(f"{prefix}.index"), entries, per_block=5, compress=compress)
    assert tfc._read_table(Path(f"{prefix}.index")) == entries
    got = read_tf_checkpoint(prefix)
    assert got.keys() == expected.keys()
    assert all(got[k].tobytes() == expected[k].tobytes() for k in got)


# ---------------------------------------------------------------------------------------------
# damaged and foreign files


def test_flipped_data_byte_is_a_crc_error(tmp_path):
    prefix = _copy("small", tmp_path)
    _, entries = list_tf_checkpoint(prefix)
    entry = entries["model/interaction_blocks/1/int_weights2/.ATTRIBUTES/VARIABLE_VALUE"]
    _flip(Path(f"{prefix}{DATA}"), entry.offset + 7)
    with pytest.raises(ChecksumError, match=r"small\.data-00000-of-00001.*int_weights2"):
        read_tf_checkpoint(prefix)
    # without verification the (corrupted) values are returned
    weights = read_tf_checkpoint(prefix, verify_crc=False)
    assert "model/interaction_blocks/1/int_weights2" in weights


def test_flipped_index_byte_is_a_block_checksum_error(tmp_path):
    prefix = _copy("small", tmp_path)
    _flip(Path(f"{prefix}.index"), 40)
    with pytest.raises(ChecksumError, match=r"small\.index.*checksum"):
        read_tf_checkpoint(prefix)


def test_truncated_data_shard(tmp_path):
    prefix = _copy("small", tmp_path)
    data = Path(f"{prefix}{DATA}")
    data.write_bytes(data.read_bytes()[:20000])
    with pytest.raises(TFCheckpointError, match=r"small\.data-00000-of-00001.*truncated"):
        read_tf_checkpoint(prefix)


@pytest.mark.parametrize("keep", [0, 30, 1000])
def test_truncated_index(tmp_path, keep):
    prefix = _copy("small", tmp_path)
    index = Path(f"{prefix}.index")
    index.write_bytes(index.read_bytes()[:keep])
    with pytest.raises(TFCheckpointError, match=r"small\.index.*truncated"):
        read_tf_checkpoint(prefix)


def test_wrong_magic(tmp_path):
    prefix = _copy("small", tmp_path)
    _flip(Path(f"{prefix}.index"), Path(f"{prefix}.index").stat().st_size - 1)
    with pytest.raises(TFCheckpointError, match=r"small\.index: bad table magic"):
        read_tf_checkpoint(prefix)


def test_not_a_checkpoint(tmp_path):
    (tmp_path / "notes.index").write_text("just some text, " * 10)
    with pytest.raises(TFCheckpointError, match=r"notes\.index.*not a TensorFlow checkpoint"):
        read_tf_checkpoint(tmp_path / "notes")


def test_table_without_bundle_header(tmp_path):
    path = tmp_path / "plain.index"
    _write_table(path, [(b"a", b""), (b"b", b"")], per_block=4, compress=False)
    with pytest.raises(TFCheckpointError, match=r"plain\.index: no bundle header"):
        list_tf_checkpoint(tmp_path / "plain")


def test_missing_files(tmp_path):
    with pytest.raises(MissingCheckpointFileError, match=r"nothing\.index"):
        read_tf_checkpoint(tmp_path / "nothing")
    prefix = _copy("small", tmp_path)
    Path(f"{prefix}{DATA}").unlink()
    with pytest.raises(MissingCheckpointFileError, match=r"small\.data-00000-of-00001"):
        read_tf_checkpoint(prefix)
    Path(f"{prefix}.pickle").unlink()
    with pytest.raises(MissingCheckpointFileError, match=r"small\.pickle"):
        read_reference_hparams(prefix)
    assert issubclass(MissingCheckpointFileError, FileNotFoundError)


# ---------------------------------------------------------------------------------------------
# restricted unpickling


class _Evil:
    def __reduce__(self):
        return (print, ("executed",))


def test_pickle_with_foreign_globals_is_refused(tmp_path, capsys):
    (tmp_path / "evil.pickle").write_bytes(pickle.dumps({"cutoff": _Evil()}))
    with pytest.raises(TFCheckpointError, match=r"evil\.pickle: refusing to unpickle builtins"):
        read_reference_hparams(tmp_path / "evil")
    assert "executed" not in capsys.readouterr().out
    (tmp_path / "cls.pickle").write_bytes(pickle.dumps({"path": Path("/")}))
    with pytest.raises(TFCheckpointError, match="refusing to unpickle pathlib"):
        read_reference_hparams(tmp_path / "cls")


def test_pickle_numpy_values_and_bad_payloads(tmp_path):
    value = {"n_max": np.int64(8), "centers": np.arange(3.0), "names": ["a"], "t": (1, 2.5)}
    (tmp_path / "np.pickle").write_bytes(pickle.dumps(value))
    loaded = read_reference_hparams(tmp_path / "np")
    assert loaded["n_max"] == 8 and isinstance(loaded["n_max"], np.int64)
    assert np.array_equal(loaded["centers"], np.arange(3.0))
    assert loaded["names"] == ["a"] and loaded["t"] == (1, 2.5)
    (tmp_path / "list.pickle").write_bytes(pickle.dumps([1, 2]))
    with pytest.raises(TFCheckpointError, match=r"list\.pickle: expected a dict"):
        read_reference_hparams(tmp_path / "list")
    (tmp_path / "cut.pickle").write_bytes(pickle.dumps({"a": 1.0})[:-3])
    with pytest.raises(TFCheckpointError, match=r"cut\.pickle: not a readable pickle"):
        read_reference_hparams(tmp_path / "cut")
