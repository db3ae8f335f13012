"""A run in Foxglove's own schemas (``export --foxglove``): every message decodes with the schema
the file carries (protobuf descriptors; the figures' JSON schema), poses and stamps are the
trajectory file's, and the layout names the file's topics."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from lidarloc.app import export_foxglove as fx
from lidarloc.core.runs import recording
from rich.console import Console


@pytest.fixture(scope="module")
def exported(recorded_town_run, cache_root, tmp_path_factory):
    run, _ = recorded_town_run
    out = tmp_path_factory.mktemp("foxglove") / "run.mcap"
    return run, out, fx.export_foxglove(run, out, console=Console(file=io.StringIO()), cache_root=cache_root)


def decode_all(path) -> dict[str, list]:
    """topic → [(log time, decoded message)], each decoded with the schema in the file: protobuf
    messages through the descriptors the schema record holds (no field the schema does not know
    may be left over), JSON messages validated against their JSON schema."""
    import jsonschema
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from google.protobuf.unknown_fields import UnknownFieldSet
    from mcap.reader import make_reader

    classes, out = {}, {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if schema.encoding == "protobuf":
                assert channel.message_encoding == "protobuf" and schema.name.startswith("foxglove.")
                if schema.id not in classes:
                    pool = descriptor_pool.DescriptorPool()
                    for fd in descriptor_pb2.FileDescriptorSet.FromString(schema.data).file:
                        pool.Add(fd)
                    classes[schema.id] = message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))
                msg = classes[schema.id].FromString(message.data)
                assert len(UnknownFieldSet(msg)) == 0
            else:
                assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json")
                msg = json.loads(message.data)
                jsonschema.validate(msg, json.loads(schema.data))
            out.setdefault(channel.topic, []).append((message.log_time, msg, schema.name))
    return out


def test_every_message_validates_against_its_schema(exported):
    run, out, result = exported
    rec = recording.open(run)
    msgs = decode_all(out)
    expected = {
        fx.POSE: "foxglove.PoseInFrame",
        fx.TRUTH: "foxglove.PoseInFrame",
        fx.TF: "foxglove.FrameTransforms",
        fx.PARTICLES: "foxglove.PosesInFrame",
        fx.PARTICLE_CLOUD: "foxglove.PointCloud",
        fx.SCAN: "foxglove.PointCloud",
        fx.MAP: "foxglove.PointCloud",
        fx.SCENE: "foxglove.SceneUpdate",
        fx.LOG: "foxglove.Log",
        fx.FIGURES: "lidarloc.Figures",
    }
    assert {t: m[0][2] for t, m in msgs.items()} == expected
    for topic in set(expected) - {fx.MAP, fx.LOG}:
        assert len(msgs[topic]) == rec.n, topic
    assert len(msgs[fx.MAP]) == 1 and len(msgs[fx.LOG]) == len(rec.events)
    assert {t: len(m) for t, m in msgs.items()} == result["messages"]
    # the S2M matches that landed are drawn (box, arrow, verdict) at their steps
    s2m = [m for _, m, _ in msgs[fx.SCENE] if any(e.id == "s2m" for e in m.entities)]
    assert len(s2m) == len(rec.s2m_steps) > 0


def test_poses_stamps_and_figures_are_the_runs(exported):
    run, out, _ = exported
    rec = recording.open(run)
    tum = np.loadtxt(run / "trajectory_tum.txt")
    msgs = decode_all(out)
    for (t, m, _), row in zip(msgs[fx.POSE], tum):
        assert abs(t - round(row[0] * 1e9)) <= 1000
        assert abs(m.timestamp.seconds * 10**9 + m.timestamp.nanos - t) == 0 and m.frame_id == "map"
        assert np.allclose([m.pose.position.x, m.pose.position.y, m.pose.position.z], row[1:4], atol=2e-6)
    figures = [m for _, m, _ in msgs[fx.FIGURES]]
    assert [f["scan"] for f in figures] == rec.scan_index.tolist()
    assert np.allclose([f["n_eff"] for f in figures], rec.n_eff)
    assert [f["localized"] for f in figures] == rec.localized.tolist()
    cloud = msgs[fx.PARTICLE_CLOUD][-1][1]
    data = np.frombuffer(cloud.data, np.float32).reshape(-1, 4)
    assert [f.name for f in cloud.fields] == ["x", "y", "z", "weight"] and cloud.point_stride == 16
    assert np.allclose(data[:, 3], rec.weights(rec.n - 1), rtol=1e-5, atol=1e-9)


def test_the_layout_opens_the_files_topics(exported):
    _, out, result = exported
    layout = json.loads(out.with_name("run.layout.json").read_text())
    assert result["layout"] == str(out.with_name("run.layout.json"))
    text = json.dumps(layout)
    panels = [p for p in ("ThreeDee", "Plot", "Log") if f'"panelType": "{p}"' in text]
    assert panels == ["ThreeDee", "Plot", "Log"]
    for topic in (fx.MAP, fx.SCAN, fx.PARTICLE_CLOUD, fx.POSE, fx.SCENE, fx.LOG):
        assert f'"{topic}' in text, topic
    for field in ("std_m", "error_m", "n_eff_share", "pf_ms", "rpe_ms", "s2m_ms"):
        assert f"{fx.FIGURES}.{field}" in text and field in fx.FIGURES_SCHEMA["properties"]


def test_a_wrong_name_is_one_line(tmp_path):
    from lidarloc.core.errors import LidarlocError

    with pytest.raises(LidarlocError, match="NAME.mcap"):
        fx.foxglove_target(tmp_path / "run.bag")
