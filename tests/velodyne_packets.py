"""Scans written as a VLP-16 would send them: data packets (1206-byte UDP payloads to port 2368)
in a pcap with Ethernet/IPv4/UDP headers, for the pcap source's tests.

A packet holds 12 blocks (0xFFEE, the block's azimuth in hundredths of a degree, 32 × (distance
in 2 mm units, reflectivity)), each two firings of the 16 lasers, then a 4-byte timestamp (µs
past the hour) and the factory bytes (0x37: strongest return, 0x22: VLP-16). The decoder gives
laser k of a firing the azimuth of its block plus the head's turn during the 2.304 µs × k and
55.296 µs it fired after the block's first laser; with firings FIRING_STEP hundredths apart that
turn is a whole k (and FIRING_STEP) hundredths, so every written point's direction is exact.
"""

from __future__ import annotations

import math
import struct
from pathlib import Path

import numpy as np

#: the VLP-16's lasers' elevations (degrees) in firing order (laser id 0 … 15)
ELEVATIONS_DEG = (-15, 1, -13, 3, -11, 5, -9, 7, -7, 9, -5, 11, -3, 13, -1, 15)
FIRING_STEP = 24  # hundredths of a degree between firings: 1500 a turn
FIRINGS = 1488  # firings written a turn: 62 packets of 24; the last 2.88° of each turn stay empty
CUT = 18000  # a turn starts straight behind the sensor, where the source cuts frames
UNIT = 0.002  # m, the distance's unit
#: m, the lasers' focal distance: each laser's origin sits FOCAL · tan(−elevation) above the
#: sensor's (the VLP-16 envelope drawing), which decoders add to z
FOCAL = 41.91e-3
PORT = 2368
PERIOD = 0.1  # s, one turn


def _ip_udp(payload: bytes, port: int) -> bytes:
    eth = b"\xff" * 6 + bytes.fromhex("607688000000") + b"\x08\x00"
    ip = struct.pack(
        ">BBHHHBBH4s4s", 0x45, 0, 28 + len(payload), 0, 0x4000, 64, 17, 0, bytes([192, 168, 1, 201]), b"\xff" * 4
    )
    return eth + ip + struct.pack(">HHHH", port, port, 8 + len(payload), 0) + payload


def slots(points: np.ndarray) -> tuple[np.ndarray, ...]:
    """Where the points of a scan go, in the order a decoder gives them back (firing, then laser):
    (the point's index, firing, laser, distance in units, reflectivity) of each point that fits a
    slot (the nearest laser within 1°, a written firing, range 0.1–130 m), the first of a slot kept."""
    x, y, z = (points[:, k].astype(np.float64) for k in range(3))
    r = np.sqrt(x * x + y * y + z * z)
    elevation = np.degrees(np.arcsin(np.clip(z / np.maximum(r, 1e-9), -1, 1)))
    gaps = np.abs(elevation[:, None] - np.asarray(ELEVATIONS_DEG)[None, :])
    laser = np.argmin(gaps, axis=1)
    azimuth = np.degrees(np.arctan2(-y, x)) * 100.0  # the sensor's azimuth turns clockwise
    firing = np.rint(((azimuth - laser - CUT) % 36000) / FIRING_STEP).astype(np.int64) % 1500
    units = np.rint(r / UNIT).astype(np.int64)
    ok = (gaps.min(axis=1) < 1.0) & (firing < FIRINGS) & (r > 0.1) & (r < 130.0)
    slot = firing * 16 + laser
    _, first = np.unique(np.where(ok, slot, -1), return_index=True)
    keep = first[ok[first]]
    keep = keep[np.argsort(slot[keep])]
    reflectivity = np.clip(np.rint(points[keep, 3] * 255.0), 0, 255).astype(np.int64)
    return keep, firing[keep], laser[keep], units[keep], reflectivity


def written_points(firing, laser, units, reflectivity) -> np.ndarray:
    """(N, 4) the points the slots hold: x, y, z as a VLP-16's decoder computes them, reflectivity."""
    f, k, d, i = firing, laser, units * UNIT, reflectivity
    azimuth = np.radians(((CUT + FIRING_STEP * f + k) % 36000) / 100.0)
    elevation = np.radians(np.asarray(ELEVATIONS_DEG, np.float64)[k])
    return np.stack(
        [
            d * np.cos(elevation) * np.cos(azimuth),
            -d * np.cos(elevation) * np.sin(azimuth),
            d * np.sin(elevation) + FOCAL * np.tan(-elevation),
            i,
        ],
        axis=1,
    )


def turn_packets(firing, laser, units, reflectivity, start: float) -> list[tuple[float, bytes]]:
    """The turn's data packets with their capture times, the first at ``start`` (s)."""
    distance = np.zeros((FIRINGS, 16), np.uint16)
    intensity = np.zeros((FIRINGS, 16), np.uint8)
    distance[firing, laser] = units
    intensity[firing, laser] = reflectivity
    packets = []
    for p in range(FIRINGS // 24):
        t = start + PERIOD * p * 24 / 1500
        blocks = []
        for b in range(12):
            f = 24 * p + 2 * b
            body = b"".join(
                struct.pack("<HB", int(distance[f + s, k]), int(intensity[f + s, k])) for s in (0, 1) for k in range(16)
            )
            blocks.append(b"\xff\xee" + struct.pack("<H", (CUT + FIRING_STEP * f) % 36000) + body)
        tail = struct.pack("<I", int(round((t % 3600) * 1e6))) + b"\x37\x22"
        packets.append((t, b"".join(blocks) + tail))
    return packets


def write_pcap(path: Path, scans: list[np.ndarray], start: float = 1_700_000_000.0) -> list[tuple[np.ndarray, ...]]:
    """Write ``scans`` as turns of a VLP-16 into a pcap, PERIOD apart from ``start`` (one position
    packet, a 512-byte payload to port 8308, before each turn). Each turn's (points written, in the
    decoder's order; the index of the scan's point each one is; their distances, m)."""
    out = [struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, 65535, 1)]
    written = []
    for n, scan in enumerate(scans):
        index, *chosen = slots(scan)
        written.append((written_points(*chosen), index, chosen[2] * UNIT))
        t0 = start + n * PERIOD
        records = [(t0 - 1e-4, _ip_udp(bytes(512), 8308))]
        records += [(t, _ip_udp(payload, PORT)) for t, payload in turn_packets(*chosen, start=t0)]
        for t, frame in records:
            sec = math.floor(t)
            usec = min(int(round((t - sec) * 1e6)), 999_999)
            out.append(struct.pack("<IIII", sec, usec, len(frame), len(frame)) + frame)
    path.write_bytes(b"".join(out))
    return written
