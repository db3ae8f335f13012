"""The Velodyne pcap source (core/sequences/sources/pcap.py): the built-in town's VLP-16 scans
written as raw packets (tests/velodyne_packets.py) come back point for point, one frame a turn,
with their truth; a damaged capture is one line. The source is the registry's: it is opened,
checked and listed through the same paths as every other source."""

import dataclasses
import importlib.util

import numpy as np
import pytest
from helpers import run_cli
from lidarloc.core.errors import DataError
from lidarloc.core.runs.results import write_tum
from lidarloc.core.sequences.factory import SourceSpec, check_spec, open_sequence
from lidarloc.core.sequences.registry import source_named
from velodyne_packets import ELEVATIONS_DEG, PERIOD, UNIT, write_pcap

needs_decoder = pytest.mark.skipif(
    importlib.util.find_spec("velodyne_decoder") is None,
    reason="velodyne-decoder is not installed (pip install 'lidarloc[pcap]')",
)
TURNS = 3
START = 1_700_000_000.0


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """The town's first TURNS scans from a VLP-16, written as a pcap; its truth as a TUM file."""
    from lidarloc.core.config import TownConfig
    from lidarloc.core.sim.town import TownSequence

    town = TownSequence.from_config(TownConfig(sensor="vlp16", n_scans=TURNS), seed=0)
    scans = [town.scan(i) for i in range(TURNS)]
    d = tmp_path_factory.mktemp("pcap")
    written = write_pcap(d / "drive.pcap", scans, start=START)
    write_tum(d / "gt.tum", START + PERIOD * np.arange(TURNS), town.poses[:TURNS])
    return d, scans, written, town.poses


@needs_decoder
def test_frames_are_the_written_turns_point_for_point(drive):
    d, scans, written, poses = drive
    seq = open_sequence(SourceSpec(pcap=d / "drive.pcap", gt=d / "gt.tum"))
    assert len(seq) == TURNS and seq.notes == []
    np.testing.assert_allclose(seq.timestamps, PERIOD * np.arange(TURNS), atol=2e-6)
    np.testing.assert_allclose(seq.poses, np.linalg.inv(poses[0])[None] @ poses[:TURNS], atol=1e-5)
    for i in range(TURNS):
        got, (want, index, distance) = seq.scan(i), written[i]
        assert got.shape == want.shape and len(got) > 0.8 * len(scans[i])  # most points found a slot
        # the points written, to float32's precision: the distances' 2 mm units on the VLP-16's
        # fixed elevations and the firings' azimuths
        np.testing.assert_allclose(got[:, :3], want[:, :3], rtol=0, atol=2e-4)
        np.testing.assert_array_equal(got[:, 3], want[:, 3])
        # … which are the town's points: each distance within half a unit of the town's range, and
        # each point within the azimuth grid's half-step (0.12°) plus the laser's 11 mm offset
        town = scans[i][index, :3].astype(np.float64)
        ranges = np.linalg.norm(town, axis=1)
        assert np.abs(distance - ranges).max() <= UNIT / 2 + 1e-6
        assert (np.linalg.norm(got[:, :3] - town, axis=1) <= ranges * np.radians(0.125) + 0.012).all()
        assert np.abs(np.degrees(np.arcsin(town[:, 2] / ranges))).max() <= max(ELEVATIONS_DEG) + 1


@needs_decoder
def test_a_damaged_capture_is_one_line(drive, tmp_path):
    d = drive[0]
    data = (d / "drive.pcap").read_bytes()
    cases = {
        "cut.pcap": (data[: len(data) - 700], "truncated: record"),
        "text.pcap": (b"x y z\n" * 10, "not a pcap file"),
        "ng.pcap": (b"\x0a\x0d\x0d\x0a" + data[4:], "a pcapng file; convert it: editcap -F pcap"),
        "hdl32.pcap": (data.replace(b"\x37\x22", b"\x37\x21"), "not from a VLP-16; give --pcap-sensor HDL-32E"),
        "empty.pcap": (data[:24], "no Velodyne data packets"),
    }
    for name, (content, message) in cases.items():
        (tmp_path / name).write_bytes(content)
        with pytest.raises(DataError, match=message) as err:
            open_sequence(SourceSpec(pcap=tmp_path / name, gt=d / "gt.tum"))
        assert "\n" not in str(err.value) and name in str(err.value)
    with pytest.raises(DataError, match="--pcap-sensor must be one of VLP-16"):
        open_sequence(SourceSpec(pcap=d / "drive.pcap", gt=d / "gt.tum", pcap_sensor="vlp16"))
    # on the command line: one line, exit status 2, no traceback
    r = run_cli("map", "build", "--pcap", tmp_path / "cut.pcap", "--gt", d / "gt.tum", cache=tmp_path / "cache")
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().count("\n") == 0 and "truncated" in r.stderr


def test_the_registry_checks_lists_and_records_it(tmp_path):
    with pytest.raises(DataError, match="--pcap-sensor names the sensor of --pcap; give --pcap FILE"):
        check_spec(SourceSpec(pcap_sensor="HDL-32E"))
    with pytest.raises(DataError, match="choose one source: --bag or --pcap, not both"):
        check_spec(SourceSpec(pcap=tmp_path / "a.pcap", bag=tmp_path / "b.bag", gt=tmp_path / "gt.tum"))
    with pytest.raises(DataError, match="a prior map needs --map FILE or ground truth"):
        check_spec(SourceSpec(pcap=tmp_path / "a.pcap"))
    spec = SourceSpec(pcap=tmp_path / "a.pcap", map=tmp_path / "m.pcd")
    assert (
        spec.kind == "pcap"
        and spec.describe() == f"Velodyne pcap {tmp_path / 'a.pcap'} (VLP-16) in map {tmp_path / 'm.pcd'}"
    )
    assert SourceSpec.from_dict(spec.to_dict()) == spec
    absent = dataclasses.replace(source_named("pcap"), requires="no_such_module_here")
    assert not absent.available()
    assert str(absent.missing()) == "--pcap needs the no_such_module_here module: pip install 'lidarloc[pcap]'"


def test_the_command_line_lists_it_from_the_registry():
    import json

    from lidarloc.app import cli
    from typer.testing import CliRunner

    listed = CliRunner().invoke(cli.app, ["sources", "--json"])
    assert listed.exit_code == 0, listed.output
    sources = {s["name"]: s for s in json.loads(listed.output)["sources"]}
    assert set(sources) == {"town", "kitti_odometry", "kitti_raw", "bag", "scans_dir", "pcap"}
    assert sources["town"]["default"] and sources["pcap"]["recording"]
    assert [o["flag"] for o in sources["pcap"]["options"]] == ["--pcap", "--pcap-sensor"]
    assert sources["pcap"]["options"][1]["default"] == "VLP-16"
    helped = CliRunner().invoke(cli.app, ["map", "build", "--help"], env={"COLUMNS": "200"})
    assert helped.exit_code == 0 and "--pcap-sensor" in helped.output and "--pcap," in helped.output
