#!/usr/bin/env python3
"""Reads a plccoms history day file without plccoms: its rows and its packed
blocks (src/historian/block.rs documents the layout), as pandas or plain
tuples. Needs the `zstandard` package (pip install zstandard); pandas only
for `frame`.

    python3 tools/history_read.py history/Boiler/Boiler-2026-05-01.sqlite

    from history_read import samples, frame
    df = frame("history/Boiler/Boiler-2026-05-01.sqlite")   # time, name, value, quality, plc_time
"""
import sqlite3
import struct
import sys
import zlib

import zstandard

QUALITY = {0: "good", 1: "stale", 2: "link_lost"}


def _varint(data, at):
    value = shift = 0
    while True:
        b = data[at]
        at += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if b < 0x80:
            return value, at


def _zigzag(data, at):
    u, at = _varint(data, at)
    return (u >> 1) ^ -(u & 1), at


def _wrap(v):
    """Two's complement 64-bit, as the block's integers wrap."""
    v &= (1 << 64) - 1
    return v - (1 << 64) if v >= 1 << 63 else v


def unseal(blob):
    """The zstd frame of a stored block: a sealed block (first byte 2) is
    checked against its CRC-32; one of file version 2 is the bare frame."""
    blob = bytes(blob)
    if blob[:1] == b"\x02":
        (crc,) = struct.unpack("<I", blob[1:5])
        if zlib.crc32(blob[5:]) != crc:
            raise ValueError("a packed block is damaged: its checksum does not match")
        return blob[5:]
    return blob


def unpack(blob):
    """A block's samples: (ms since the day's start, var id, value, quality, plc ms or None)."""
    data = zstandard.ZstdDecompressor().decompressobj().decompress(unseal(blob))
    if data[0] != 1:
        raise ValueError(f"block encoding {data[0]}")
    first_ms, at = _varint(data, 1)
    n, at = _varint(data, at)
    nruns, at = _varint(data, at)
    runs, var = [], 0
    for _ in range(nruns):
        step, at = _varint(data, at)
        count, at = _varint(data, at)
        var += step
        runs.append((var, count))
    times, run_of = [], []
    for r, (_, count) in enumerate(runs):
        delta = 0
        for j in range(count):
            if j == 0:
                offset, at = _varint(data, at)
                ms = first_ms + offset
            else:
                dd, at = _zigzag(data, at)
                delta += dd
                ms += delta
            times.append(ms)
            run_of.append(r)
    kinds = data[at:at + n]
    at += n
    values = [None] * n
    reals = []
    previous_int, current = 0, -1
    for i, kind in enumerate(kinds):
        if run_of[i] != current:
            current, previous_int = run_of[i], 0
        if kind == 1:
            d, at = _zigzag(data, at)
            previous_int = _wrap(previous_int + d)
            values[i] = previous_int
        elif kind == 2:
            reals.append(i)
        elif kind not in (0, 3):
            raise ValueError(f"value kind {kind}")
    count = len(reals)
    bits, current = 0, -1
    for k, i in enumerate(reals):
        xor = 0
        for plane in range(8):
            xor = (xor << 8) | data[at + plane * count + k]
        if run_of[i] != current:
            current, bits = run_of[i], 0
        bits ^= xor
        values[i] = struct.unpack(">d", bits.to_bytes(8, "big"))[0]
    at += 8 * count
    for i, kind in enumerate(kinds):
        if kind == 3:
            length, at = _varint(data, at)
            values[i] = data[at:at + length].decode("utf-8")
            at += length
    qualities = data[at:at + n]
    at += n
    stamps = [None] * n
    nstamps, at = _varint(data, at)
    index = 0
    for _ in range(nstamps):
        step, at = _varint(data, at)
        index += step
        offset, at = _zigzag(data, at)
        stamps[index] = times[index] + offset
    return [(times[i], runs[run_of[i]][0], values[i], qualities[i], stamps[i]) for i in range(n)]


def samples(path):
    """Every sample of a day file in time order: (UTC ms, name, value, quality, PLC ms or None)."""
    db = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    meta = dict(db.execute("SELECT key, value FROM meta"))
    start, bits = int(meta["day_start_ms"]), int(meta["var_bits"])
    names = dict(db.execute("SELECT id, name FROM vars"))
    out = []
    has_blocks = db.execute("SELECT count(*) FROM sqlite_master WHERE name = 'blocks'").fetchone()[0]
    if has_blocks:
        for (blob,) in db.execute("SELECT data FROM blocks ORDER BY first_key"):
            for ms, var, value, quality, plc in unpack(blob):
                out.append((start + ms, names[var], value, QUALITY[quality], plc, ms << bits | var))
    rows = db.execute(
        "SELECT s.key, s.value, coalesce(q.quality, 0), st.plc_time FROM samples s "
        "LEFT JOIN qualities q ON q.key = s.key LEFT JOIN stamps st ON st.key = s.key")
    mask = (1 << bits) - 1
    for key, value, quality, plc in rows:
        out.append((start + (key >> bits), names[key & mask], value, QUALITY[quality], plc, key))
    out.sort(key=lambda s: s[5])
    return [s[:5] for s in out]


def frame(path):
    import pandas as pd
    df = pd.DataFrame(samples(path), columns=["time_ms", "name", "value", "quality", "plc_time_ms"])
    df.insert(0, "time", pd.to_datetime(df["time_ms"], unit="ms", utc=True))
    return df


if __name__ == "__main__":
    for t, name, value, quality, plc in samples(sys.argv[1]):
        print(t, name, value, quality, "" if plc is None else plc, sep=",")
