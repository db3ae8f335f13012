"""Raw Velodyne packets in a ``.pcap`` capture as a source: ``--pcap FILE [--pcap-sensor MODEL]``,
decoded with the ``velodyne-decoder`` package (``pip install 'lidarloc[pcap]'``).

**Packets.** The capture's UDP payloads of 1206 bytes that start with a data block's 0xFFEE
flag are the sensor's data packets (from port 2368 by default; any port is read); everything else
(position packets, other traffic) is skipped. Ethernet (with or without a VLAN tag), Linux cooked
and raw IPv4 captures are read, in microsecond or nanosecond pcap files of either byte order;
pcapng files are refused with the command that converts them.

**Frames.** A frame is one full rotation of the head, cut where it passes straight behind the
sensor (azimuth 180°), at packet boundaries: the sweep convention of
:mod:`lidarloc.core.odometry.deskew`. A partial turn at the start or end of the capture is left
out, with a note. A frame's time is the capture time of its first packet (the pcap's clock, which
``--gt`` times must share). Points are x forward, y left, z up in the sensor frame (the ROS
driver's convention), intensity the sensor's reflectivity (0–255) as the ROS driver gives it.

**Truth and map** are a recording's (:mod:`lidarloc.core.sequences.scan_folder`): ``--gt`` TUM or
KITTI poses matched by time, ``--extrinsic`` base ← LiDAR, or ``--map FILE``.

**Cost.** Opening reads the capture's packet headers once (the index: a few bytes a packet); a
frame is read and decoded on demand, so memory does not grow with the capture's length.
"""

from __future__ import annotations

import hashlib
import mmap
import struct
from pathlib import Path

import numpy as np

from ...cache import array_digest, file_identity
from ...errors import DataError
from ..base import RecordedSequence
from ..extrinsic import resolve_extrinsic
from ..groundtruth import MATCH_TOL_S, truth_of_recording
from ..registry import Option, Source, as_path, truth_options

PAYLOAD = 1206  # a Velodyne data packet: 12 blocks of 100 bytes, a 4-byte timestamp, 2 factory bytes
FLAG = b"\xff\xee"  # every data block starts with it
CUT = 18000  # azimuth where frames are cut (hundredths of a degree): straight behind
#: --pcap-sensor's names → (velodyne_decoder.Model's name, the model's factory byte in each packet)
MODELS = {
    "VLP-16": ("VLP16", 0x22),
    "Puck-Hi-Res": ("PuckHiRes", 0x24),
    "HDL-32E": ("HDL32E", 0x21),
    "VLP-32A": ("VLP32A", 0x23),
    "VLP-32B": ("VLP32B", 0x23),
    "VLP-32C": ("VLP32C", 0x28),
    "VLS-128": ("VLS128", 0xA1),
}
_MAGIC = {
    b"\xd4\xc3\xb2\xa1": ("<", 1e-6),
    b"\xa1\xb2\xc3\xd4": (">", 1e-6),
    b"\x4d\x3c\xb2\xa1": ("<", 1e-9),
    b"\xa1\xb2\x3c\x4d": (">", 1e-9),
}
_LINK_HEADER = {1: 14, 113: 16, 276: 20, 101: 0, 228: 0}  # Ethernet, Linux cooked v1/v2, raw IPv4
_MAX_RECORD = 1 << 18


def _udp_payload(frame: memoryview, link: int) -> tuple[int, int] | None:
    """(offset, length) of the UDP payload in one captured frame, or None (not IPv4/UDP)."""
    at = _LINK_HEADER[link]
    if link == 1:
        ethertype = int.from_bytes(frame[12:14], "big") if len(frame) >= 14 else 0
        if ethertype == 0x8100 and len(frame) >= 18:  # one VLAN tag
            ethertype, at = int.from_bytes(frame[16:18], "big"), 18
        if ethertype != 0x0800:
            return None
    if len(frame) < at + 28 or frame[at] >> 4 != 4 or frame[at + 9] != 17:
        return None
    if int.from_bytes(frame[at + 6 : at + 8], "big") & 0x3FFF:  # a fragment
        return None
    udp = at + (frame[at] & 0x0F) * 4
    length = int.from_bytes(frame[udp + 4 : udp + 6], "big") - 8
    return udp + 8, min(length, len(frame) - udp - 8)


def index_packets(path: Path, progress=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The capture's Velodyne data packets: their payloads' offsets in the file, capture times (s)
    and first blocks' azimuths (hundredths of a degree). A file that is not a pcap, or is cut
    short, is a one-line DataError."""
    size = path.stat().st_size
    if size < 24:
        raise DataError(f"{path}: not a pcap file ({size} bytes)")
    offsets: list[int] = []
    stamps: list[float] = []
    azimuths: list[int] = []
    with open(path, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as data:
        head = data[:4]
        if head == b"\x0a\x0d\x0d\x0a":
            raise DataError(f"{path}: a pcapng file; convert it: editcap -F pcap {path.name} out.pcap")
        if head not in _MAGIC:
            raise DataError(f"{path}: not a pcap file (its first bytes are {head.hex()})")
        order, tick = _MAGIC[head]
        (link,) = struct.unpack_from(order + "I", data, 20)
        if link not in _LINK_HEADER:
            raise DataError(f"{path}: link type {link} is not read (Ethernet, Linux cooked or raw IPv4)")
        record = struct.Struct(order + "IIII")
        view = memoryview(data)
        at, k = 24, 0
        try:
            while at < size:
                if at + 16 > size:
                    raise DataError(f"{path}: truncated: record {k} header cut at byte {at} of {size}")
                sec, frac, length, _ = record.unpack_from(data, at)
                if length > _MAX_RECORD:
                    raise DataError(f"{path}: corrupt: record {k} at byte {at} claims {length} bytes")
                if at + 16 + length > size:
                    raise DataError(
                        f"{path}: truncated: record {k} at byte {at} needs {length} bytes, {size - at - 16} left"
                    )
                found = _udp_payload(view[at + 16 : at + 16 + length], link)
                payload = at + 16 + found[0] if found is not None else 0
                if found is not None and found[1] == PAYLOAD and data[payload : payload + 2] == FLAG:
                    offsets.append(payload)
                    stamps.append(sec + frac * tick)
                    azimuths.append(int.from_bytes(data[payload + 2 : payload + 4], "little"))
                at += 16 + length
                k += 1
                if progress is not None and k % 2000 == 0:
                    progress(at, size)
        finally:
            view.release()
    if not offsets:
        raise DataError(f"{path}: no Velodyne data packets (UDP payloads of {PAYLOAD} bytes starting with 0xFFEE)")
    return np.asarray(offsets, np.int64), np.asarray(stamps, np.float64), np.asarray(azimuths, np.int64)


def split_rotations(azimuths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames of packets whose first blocks' ``azimuths`` (hundredths of a degree) are given:
    (first packet, end packet) of each full turn, cut behind the sensor, and whether a partial
    turn was left out at either end."""
    turned = (azimuths.astype(np.int64) - CUT) % 36000
    starts = np.concatenate([[0], np.flatnonzero(np.diff(turned) < 0) + 1])
    ends = np.append(starts[1:], len(turned))
    steps = np.diff(turned)
    step = float(np.median(steps[steps > 0])) if (steps > 0).any() else 36000.0
    covered = turned[ends - 1] - turned[starts] + step
    full = covered >= 36000 - 1.5 * step
    return np.stack([starts[full], ends[full]], axis=1), ~full


class PcapSequence(RecordedSequence):
    """The frames of a Velodyne pcap (the module docstring)."""

    def __init__(self, path, sensor: str = "VLP-16", gt=None, extrinsic=None, gt_times=None, progress=None):
        self.path = Path(path)
        if sensor not in MODELS:
            raise DataError(f"--pcap-sensor must be one of {', '.join(MODELS)}; got {sensor!r}")
        if not self.path.is_file():
            raise DataError(f"{self.path}: pcap file not found")
        self.sensor = sensor
        self.name = f"pcap {self.path.name}"
        self.notes: list[str] = []
        offsets, stamps, azimuths = index_packets(self.path, progress)
        self._check_model(int(self._read(offsets[:1])[0][PAYLOAD - 1]))
        frames, partial = split_rotations(azimuths)
        if not len(frames):
            raise DataError(f"{self.path}: no full rotation in its {len(offsets)} data packets")
        if partial.any():
            self.notes.append(f"{self.path}: {int(partial.sum())} partial rotation(s) at the start or end left out")
        self._offsets, self._frames = offsets, frames
        frame_stamps = stamps[frames[:, 0]]
        self.T_base_lidar = resolve_extrinsic(extrinsic)
        self._poses, self.truth_origin, self._gt_identity = None, None, ""
        if gt is not None:
            matched = truth_of_recording(gt, gt_times, frame_stamps, self.T_base_lidar, MATCH_TOL_S)
            self.notes += matched.notes
            self._frames, frame_stamps = frames[matched.keep], frame_stamps[matched.keep]
            self.truth_origin, self._poses, self._gt_identity = matched.origin, matched.rebased, matched.identity
        self._packet_stamps = stamps
        self.stamps = frame_stamps
        self._times = frame_stamps - frame_stamps[0]

    def _check_model(self, factory_byte: int) -> None:
        expected = MODELS[self.sensor][1]
        if factory_byte != expected:
            said = [name for name, (_, byte) in MODELS.items() if byte == factory_byte]
            hint = (
                f"give --pcap-sensor {said[0]}" if said else f"a model this source does not read ({factory_byte:#04x})"
            )
            raise DataError(f"{self.path}: the packets are not from a {self.sensor}; {hint}")

    def _read(self, offsets: np.ndarray, length: int = PAYLOAD) -> list[bytes]:
        """``length`` bytes at each offset (one read of the span they cover)."""
        first, last = int(offsets[0]), int(offsets[-1]) + length
        with open(self.path, "rb") as f:
            f.seek(first)
            span = f.read(last - first)
        if len(span) < last - first:
            raise DataError(f"{self.path}: shorter than when it was opened (changed since?)")
        return [span[o - first : o - first + length] for o in offsets.tolist()]

    def __len__(self) -> int:
        return len(self._frames)

    def describe_scan(self, i: int) -> str:
        a, b = self._frames[i]
        return f"{self.path} frame {i} (packets {a}–{b - 1}, {self.stamps[i]:.6f} s)"

    def _read_scan(self, i: int) -> np.ndarray:
        import velodyne_decoder as vd

        a, b = (int(v) for v in self._frames[i])
        packets = vd.PacketVector()
        for stamp, payload in zip(self._packet_stamps[a:b].tolist(), self._read(self._offsets[a:b])):
            packets.append(vd.VelodynePacket(stamp, payload))
        config = vd.Config(model=getattr(vd.Model, MODELS[self.sensor][0]), timestamp_first_packet=True)
        try:
            _, points = vd.ScanDecoder(config).decode(packets)
        except (RuntimeError, ValueError) as exc:
            raise DataError(f"{self.describe_scan(i)}: {' '.join(str(exc).split())}") from None
        return np.ascontiguousarray(points[:, :4], dtype=np.float32)

    def identity(self) -> str:
        frames = hashlib.sha1(self._frames.tobytes()).hexdigest()[:12]
        return (
            f"pcap|{file_identity(self.path)}|{self.sensor}|{frames}|gt={self._gt_identity}"
            f"|ext={array_digest(self.T_base_lidar)}"
        )


def _open(spec, cfg, progress=None):
    return PcapSequence(as_path(spec.pcap), sensor=spec.pcap_sensor, progress=progress, **truth_options(spec))


SOURCE = Source(
    name="pcap",
    title="raw Velodyne packets in a .pcap capture (VLP-16 by default), one frame a rotation",
    options=(
        Option("pcap", Path, "Velodyne .pcap capture of raw data packets (UDP, port 2368).", metavar="FILE"),
        Option(
            "pcap_sensor",
            str,
            "The Velodyne model of --pcap.",
            default="VLP-16",
            metavar="|".join(MODELS),
            what="names the sensor",
        ),
    ),
    open=_open,
    describe=lambda spec: f"Velodyne pcap {spec.pcap} ({spec.pcap_sensor})",
    recording=True,
    indexes=True,
    requires="velodyne_decoder",
    install="pip install 'lidarloc[pcap]'",
)
