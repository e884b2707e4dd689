"""A Rerun recording file made byte-stable: the same logging gives the same bytes.

rerun-sdk (0.41) stamps what it writes with the clock and with chance: every row and chunk id is a TUID (time in ns
and a random start of a counter), each store's info message carries one, a blueprint store gets a random id, the
blueprint's rows a ``log_time``, and the file's footer (an index of the chunks for random access) lists them in hash
order. :func:`make_stable` rewrites a finished ``.rrd`` file message by message: row ids and chunk ids by their rank
in the file (so their order, which decides what a viewer shows when two rows share a time, is kept), a blueprint
store's id from its application id, ``log_time`` 0, and no footer (the legacy layout every viewer reads from the
start; ``rerun rrd migrate`` adds one). The data themselves are not touched.

The file: a 12-byte header, then messages, each a little-endian u64 kind and u64 length and that many bytes of
protobuf: 1 SetStoreInfo (field 1: the row id), 2 ArrowMsg (1 store id, 2 compression: 2 is LZ4 block, 3 the
uncompressed size, 5 the Arrow IPC stream of one chunk, 6 the chunk id), 3 BlueprintActivationCommand, 0 the end
(its body the footer).
"""

from __future__ import annotations

import hashlib
import re
import struct
from pathlib import Path

import numpy as np
import pyarrow as pa

HEADER = 12
END, STORE_INFO, ARROW, ACTIVATE = 0, 1, 2, 3
LZ4 = 2
ROW_ID = "rerun.controls.RowId"
CHUNK_ID = b"rerun:id"
_BLUEPRINT_ID = re.compile(rb"rec_[0-9a-f]{32}")

Field = tuple[int, int, "int | bytes"]
# a TUID in an Arrow column: its 16 bytes are the big-endian time, then the counter, so that they sort as they compare
TUID = np.dtype([("time_ns", ">u8"), ("inc", ">u8")])


def _varint(buf: bytes, i: int) -> tuple[int, int]:
    value = shift = 0
    while True:
        byte = buf[i]
        i += 1
        value |= (byte & 0x7F) << shift
        shift += 7
        if byte < 0x80:
            return value, i


def _enc_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        low, value = value & 0x7F, value >> 7
        out.append(low | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _fields(buf: bytes) -> list[Field]:
    """A protobuf message as (field number, wire type, value) in order."""
    i, out = 0, list[Field]()
    while i < len(buf):
        key, i = _varint(buf, i)
        number, wire = key >> 3, key & 7
        value: int | bytes
        if wire == 0:
            value, i = _varint(buf, i)
        elif wire in (1, 5):
            size = 8 if wire == 1 else 4
            value, i = buf[i : i + size], i + size
        elif wire == 2:
            n, i = _varint(buf, i)
            value, i = buf[i : i + n], i + n
        else:
            raise ValueError(f"protobuf wire type {wire} not expected in a Rerun message")
        out.append((number, wire, value))
    return out


def _encode(fields: list[Field]) -> bytes:
    out = bytearray()
    for number, wire, value in fields:
        out += _enc_varint(number << 3 | wire)
        if wire == 0:
            out += _enc_varint(int(value))
        elif isinstance(value, bytes):
            out += (_enc_varint(len(value)) if wire == 2 else b"") + value
        else:
            raise TypeError(f"protobuf field {number}: wire type {wire} needs bytes, got {type(value).__name__}")
    return bytes(out)


def _tuid_message(time_ns: int, inc: int) -> bytes:
    """A TUID as a protobuf message (fixed64 time_ns = 1, fixed64 inc = 2)."""
    return _encode([(1, 1, struct.pack("<Q", time_ns)), (2, 1, struct.pack("<Q", inc))])


def _messages(data: bytes) -> list[tuple[int, bytes]]:
    pos, out = HEADER, []
    while pos < len(data):
        kind, size = struct.unpack_from("<QQ", data, pos)
        pos += 16
        out.append((kind, data[pos : pos + size]))
        pos += size
        if kind == END:
            break
    return out


def _chunks(fields: list[Field]) -> list[pa.RecordBatch]:
    d = {number: value for number, _, value in fields}
    payload = bytes(d[5])
    if d.get(2) == LZ4:
        payload = pa.decompress(payload, decompressed_size=int(d[3]), codec="lz4_raw", asbytes=True)
    return list(pa.ipc.open_stream(pa.py_buffer(payload)))


def _stable_batch(rb: pa.RecordBatch, ranks: np.ndarray, chunk_rank: dict[bytes, int]) -> pa.RecordBatch:
    """One chunk with its row ids by their ``ranks`` (TUID time 1, counter the rank), its chunk id by rank and its
    log_time 0."""
    columns = []
    for field, column in zip(rb.schema, rb.columns, strict=True):
        if field.name == ROW_ID:
            tuids = np.empty(len(column), TUID)
            tuids["time_ns"], tuids["inc"] = 1, ranks
            column = pa.FixedSizeBinaryArray.from_buffers(column.type, len(column), [None, pa.py_buffer(tuids)])
        elif field.name == "log_time":
            column = pa.array([0] * len(column), column.type)
        columns.append(column)
    meta = dict(rb.schema.metadata or {})
    if CHUNK_ID in meta:
        meta[CHUNK_ID] = f"chunk_{2:016X}{chunk_rank[meta[CHUNK_ID]]:016X}".encode()
    return pa.RecordBatch.from_arrays(columns, schema=rb.schema.with_metadata(meta))


def make_stable(path: Path) -> None:
    """Rewrite the ``.rrd`` file ``path`` in place so that the same logging gives the same bytes (module doc)."""
    path = Path(path)
    data = path.read_bytes()
    if data[:4] != b"RRF2":
        raise ValueError(f"{path}: not a Rerun recording (no RRF2 header)")
    messages = [(kind, _fields(body)) for kind, body in _messages(data) if kind != END]
    batches = {i: _chunks(f) for i, (kind, f) in enumerate(messages) if kind == ARROW}
    keys = [(i, j) for i, bs in batches.items() for j in range(len(bs))]
    ranks = dict(zip(keys, _ranks([_row_ids(batches[i][j]) for i, j in keys]), strict=True))

    def first_row(i: int) -> int:
        return min((int(ranks[i, j].min()) for j in range(len(batches.get(i, []))) if ranks[i, j].size), default=0)

    # the stores one after the other (the SDK interleaves them as its threads flush), each store's info first, its
    # chunks in the order of their first rows, the blueprint's activation last
    order = sorted(range(len(messages)), key=lambda i: (*_place(*messages[i]), first_row(i)))
    chunk_rank: dict[bytes, int] = {}
    for i in order:
        for rb in batches.get(i, []):
            chunk_rank.setdefault((rb.schema.metadata or {}).get(CHUNK_ID, b""), len(chunk_rank) + 1)
    out = bytearray(data[:HEADER])
    for i in order:
        kind, fields = messages[i]
        fields = [(n, w, _blueprint_id(v) if w == 2 and not (kind == ARROW and n == 5) else v) for n, w, v in fields]
        if kind == STORE_INFO:
            fields = [(n, w, _tuid_message(3, 1) if n == 1 else v) for n, w, v in fields]
        elif kind == ARROW:
            stable = [_stable_batch(rb, ranks[i, j], chunk_rank) for j, rb in enumerate(batches[i])]
            sink = pa.BufferOutputStream()
            with pa.ipc.new_stream(sink, stable[0].schema) as writer:
                for rb in stable:
                    writer.write_batch(rb)
            raw = sink.getvalue().to_pybytes()
            compressed = dict((n, v) for n, _, v in fields).get(2) == LZ4
            chunk = chunk_rank[(batches[i][0].schema.metadata or {}).get(CHUNK_ID, b"")]
            payload = pa.compress(raw, codec="lz4_raw", asbytes=True) if compressed else raw
            new = {3: len(raw), 5: payload, 6: _tuid_message(2, chunk)}
            fields = [(n, w, new.get(n, v)) for n, w, v in fields]
        body = _encode(fields)
        out += struct.pack("<QQ", kind, len(body)) + body
    out += struct.pack("<QQ", END, 0)
    tmp = path.with_name(f".{path.name}.stable")
    tmp.write_bytes(bytes(out))
    tmp.replace(path)


def _place(kind: int, fields: list[Field]) -> tuple[int, int]:
    """(store kind: 1 recording, 2 blueprint; 0 info, 1 chunk, 2 activation) of a message."""
    d = {n: v for n, _, v in fields}
    if kind == STORE_INFO:
        info = {n: v for n, _, v in _fields(bytes(d.get(2, b"")))}
        store = bytes(info.get(2, b""))
    else:
        store = bytes(d.get(1, b""))
    store_kind = next((int(v) for n, w, v in _fields(store) if n == 1 and w == 0), 0)
    return store_kind, {STORE_INFO: 0, ARROW: 1}.get(kind, 2)


def _row_ids(rb: pa.RecordBatch) -> np.ndarray:
    """A chunk's row ids as :data:`TUID` records (none when it has no row id column)."""
    i = rb.schema.get_field_index(ROW_ID)
    if i < 0:
        return np.empty(0, TUID)
    column = rb.column(i)
    return np.frombuffer(column.buffers()[1], TUID)[column.offset : column.offset + len(column)]


def _ranks(ids: list[np.ndarray]) -> list[np.ndarray]:
    """Each array of row ids by rank (1, 2, ...) among the distinct ids of them all, in byte order (a TUID's)."""
    every = np.concatenate([np.empty(0, TUID), *ids])
    order = np.lexsort((every["inc"], every["time_ns"]))
    seen = every[order]
    new = np.ones(seen.size, dtype=bool)
    new[1:] = (seen["time_ns"][1:] != seen["time_ns"][:-1]) | (seen["inc"][1:] != seen["inc"][:-1])
    rank = np.empty(seen.size, dtype=np.int64)
    rank[order] = np.cumsum(new)
    return np.split(rank, np.cumsum([x.size for x in ids])[:-1]) if ids else []


def _blueprint_id(value: int | bytes) -> int | bytes:
    """A blueprint store's random id ("rec_" and 32 hex digits) replaced by one of the same length, fixed."""
    fixed = b"rec_" + hashlib.sha256(b"flexjoint blueprint").hexdigest()[:32].encode()
    return _BLUEPRINT_ID.sub(fixed, value) if isinstance(value, bytes) else value
