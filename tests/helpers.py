"""Shared test helpers: small data builders, fakes that replace a block, and polling waits.
Test files import from here (``from helpers import …``), never from each other."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from lidarloc.core.config import Config, PFConfig, load_config
from lidarloc.core.filter.scanprep import voxel_downsample_random
from lidarloc.core.geometry import inv_pose, pose_matrix, transform_points
from lidarloc.core.sequences.base import Sequence


# ---------------------------------------------------------------------------------- configs
def paper_pf(**kw) -> PFConfig:
    """The paper's particle filter (its likelihood untempered over every point, a fixed particle
    count; the ``paper`` preset) with ``kw`` on top: what tests of the filter's own mechanics
    use, whatever the defaults are."""
    return replace(load_config(None, preset="paper").pf, **kw)


# ---------------------------------------------------------------------------------- pyright
#: the test that runs pyright over the repository (tests/test_code_quality.py)
PYRIGHT_TEST = "test_code_quality.py::test_pyright_resolves_every_import_and_is_clean"


class PyrightRun:
    """pyright over the repository, started and left running; ``result()`` waits for its answer.
    It keeps the tests' priority: niced, a busy shared machine starves it for longer than its
    test's timeout. Its output goes to files, so a long report never stalls it while nobody
    reads."""

    def __init__(self, exe: str, root: Path):
        import subprocess
        import tempfile

        self._out, self._err = tempfile.TemporaryFile("w+"), tempfile.TemporaryFile("w+")
        self.process = subprocess.Popen(
            [exe],
            cwd=root,
            stdout=self._out,
            stderr=self._err,
            text=True,
            start_new_session=True,  # one process group: its node process is ended with it
        )

    def result(self, timeout: float) -> tuple[int, str, str]:
        """(exit status, stdout, stderr), once pyright has finished."""
        code = self.process.wait(timeout=timeout)
        self._out.seek(0)
        self._err.seek(0)
        return code, self._out.read(), self._err.read()

    def stop(self) -> None:
        import os
        import signal

        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait()
        self._out.close()
        self._err.close()


def start_pyright() -> PyrightRun | str:
    """pyright over the repository as ``./run`` sets it up, started: its run, or why it cannot
    run here (a string). pyright reads the project's .venv, where ``./run`` links the repository
    as ``lidarloc`` (made here if missing)."""
    import shutil
    import sys

    root = Path(__file__).resolve().parents[1]
    if Path(sys.prefix).resolve() != (root / ".venv").resolve():
        return "pyright reads the project's .venv (run the tests with ./run test)"
    exe = Path(sys.executable).parent / "pyright"
    found = str(exe) if exe.is_file() else shutil.which("pyright")
    if found is None:
        return "pyright is not installed (it is in the test extras: pip install -e '.[test]')"
    link = Path(sys.prefix) / "src" / "lidarloc"  # what ./run makes: `lidarloc` for tests and examples
    if not link.exists():
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to("../..", target_is_directory=True)
    return PyrightRun(found, root)


# ---------------------------------------------------------------------------------- the command line
def run_cli(*args, cache, timeout: float = 300.0):
    """``lidarloc ARGS`` in a child process, as a user runs it: its maps cached in ``cache`` (not
    the user's), an environment with nothing of the caller's in it but PATH (no LIDARLOC_DATA or
    LIDARLOC_CACHE of the machine). The timeout only bounds a failure."""
    import subprocess
    import sys

    return subprocess.run(
        [sys.executable, "-m", "lidarloc.app.cli", *map(str, args)],
        capture_output=True,
        text=True,
        env={"LIDARLOC_CACHE": str(cache), "PATH": "/usr/bin:/bin"},
        timeout=timeout,
    )


def cli_here(*args, cache):
    """``lidarloc ARGS`` run by its entry point in this process, for the quick commands and the
    refusals whose output is what a test checks: what ``run_cli`` returns (status, stdout, stderr)
    without a child's second or two of imports. The environment holds none of the caller's
    LIDARLOC_ variables but its LIDARLOC_CACHE, and the signal handlers the command installs are
    put back after it. At least one test a command keeps on ``run_cli``: the command as started."""
    import contextlib
    import io
    import os
    import signal
    import subprocess
    import sys

    from lidarloc.app.cli import main

    handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    env = {k: v for k, v in os.environ.items() if k.startswith("LIDARLOC_")}
    argv = sys.argv
    out, err = io.StringIO(), io.StringIO()
    code: int | str | None = 0
    for k in env:
        del os.environ[k]
    os.environ["LIDARLOC_CACHE"] = str(cache)
    sys.argv = ["lidarloc", *map(str, args)]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            main()
    except SystemExit as exc:
        code = exc.code
    finally:
        sys.argv = argv
        del os.environ["LIDARLOC_CACHE"]
        os.environ.update(env)
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    if isinstance(code, str):  # sys.exit("…"): Python prints it and exits with 1
        err.write(code + "\n")
    status = code if isinstance(code, int) else (0 if code is None else 1)
    return subprocess.CompletedProcess(["lidarloc", *map(str, args)], status, out.getvalue(), err.getvalue())


# ---------------------------------------------------------------------------------- waiting
def wait_for(cond, timeout=60.0, what="condition"):
    """Poll until cond() holds. The timeout only bounds a failure: generous, because the CI
    machine is slower than ours and a passing test returns as soon as cond() holds."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return
        time.sleep(0.01)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")


def process_gone(pid: int) -> bool:
    """Whether process ``pid`` has exited (a zombie not yet reaped counts as exited)."""
    import psutil

    try:
        return psutil.Process(pid).status() == psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return True


#: a georeferenced map file's offset (UTM-sized easting and northing), metres
UTM_SHIFT = np.array([500_000.0, 4_000_000.0, 0.0])


# ---------------------------------------------------------------------------------- KITTI odometry tree
Tr_KITTI = np.array(
    [
        [4.276802385584e-04, -9.999672484946e-01, -8.084491683471e-03, -1.198459927713e-02],
        [-7.210626507497e-03, 8.081198471645e-03, -9.999413164504e-01, -5.403984729748e-02],
        [9.999738645903e-01, 4.859485810390e-04, -7.206933692422e-03, -2.921968648686e-01],
        [0, 0, 0, 1],
    ]
)


def make_odometry(root: Path, n_scans=3, n_poses=None, n_points=500, seq="00"):
    """A tiny KITTI odometry tree; the scans are random points (content does not matter here)."""
    rng = np.random.default_rng(0)
    d = root / "sequences" / seq / "velodyne"
    d.mkdir(parents=True)
    for i in range(n_scans):
        pts = rng.normal(0, 10, (n_points, 4)).astype(np.float32)
        pts.tofile(d / f"{i:06d}.bin")
    P = "P{}: 7.0e+02 0 6.0e+02 0 0 7.0e+02 1.8e+02 0 0 0 1 0"
    lines = [P.format(i) for i in range(4)] + ["Tr: " + " ".join(f"{v:.12e}" for v in Tr_KITTI[:3].ravel())]
    (root / "sequences" / seq / "calib.txt").write_text("\n".join(lines) + "\n")
    (root / "sequences" / seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(n_scans)))
    (root / "poses").mkdir()
    n_poses = n_scans if n_poses is None else n_poses
    with open(root / "poses" / f"{seq}.txt", "w") as f:
        for i in range(n_poses):
            T = pose_matrix(i * 1.0, 0.1 * i, 0, 0.01 * i, 0, 0)
            f.write(" ".join(f"{v:.9e}" for v in T[:3].ravel()) + "\n")
    return root


# ---------------------------------------------------------------------------------- a toy world (PF)
def toy_map() -> np.ndarray:
    """40 × 40 m of flat ground, an L of two 4 m walls (x = 0 and y = 0) and a 2 × 2 m pillar:
    every x-y position has its own view of the walls."""
    sp = 0.2
    gx, gy = np.meshgrid(np.arange(0, 40, 0.25), np.arange(0, 40, 0.25), indexing="ij")
    ground = np.c_[gx.ravel(), gy.ravel(), np.zeros(gx.size)]
    wy, wz = np.meshgrid(np.arange(0, 40, sp), np.arange(0, 4, sp), indexing="ij")
    wall_a = np.c_[np.zeros(wy.size), wy.ravel(), wz.ravel()]
    wx, wz = np.meshgrid(np.arange(0, 25, sp), np.arange(0, 4, sp), indexing="ij")
    wall_b = np.c_[wx.ravel(), np.zeros(wx.size), wz.ravel()]
    s, z = np.meshgrid(np.arange(0, 2, sp), np.arange(0, 3, sp), indexing="ij")
    s, z = s.ravel(), z.ravel()
    pillar = np.concatenate(
        [
            np.c_[30 + s, 25 + 0 * s, z],
            np.c_[30 + s, 27 + 0 * s, z],
            np.c_[30 + 0 * s, 25 + s, z],
            np.c_[32 + 0 * s, 25 + s, z],
        ]
    )
    return np.concatenate([ground, wall_a, wall_b, pillar]).astype(np.float32)


def toy_scan(world: np.ndarray, state: np.ndarray, rng, k: int) -> np.ndarray:
    """What a sensor at ``state`` sees (25 m range, 2 cm noise), prepared at 0.5 m."""
    T = pose_matrix(*state[:6])
    near = world[np.linalg.norm(world[:, :2] - state[:2], axis=1) < 25]
    local = transform_points(inv_pose(T), near) + rng.normal(0, 0.02, (len(near), 3))
    return voxel_downsample_random(local, 0.5, k)


# ---------------------------------------------------------------------------------- 2D walls (BEV, M3RSM)
def random_segments(rng, n, extent, length, step=0.1):
    """Points along n random wall segments inside [0, extent]²."""
    pts = []
    for _ in range(n):
        a = rng.uniform(0, extent, 2)
        b = a + rng.uniform(-length, length, 2)
        t = np.arange(0, 1, step / max(np.linalg.norm(b - a), step))[:, None]
        pts.append(a + (b - a) * t)
    return np.concatenate(pts)


# ---------------------------------------------------------------------------------- localizer fakes
def scripted_std(loc, stds):
    """Replace the filter's reported std with a script (the rest of the estimate is real)."""
    real = loc.pf.estimate
    calls = iter(stds)

    def estimate():
        est = real()
        try:
            s = next(calls)
        except StopIteration:
            return est
        return replace(est, std_xyz=np.array([s, s, s], dtype=float))

    loc.pf.estimate = estimate


def instant_matcher(loc, accepted=False, before=None):
    """Replace the in-process matcher (localize.s2m_process=False) with one that answers at once,
    accepting or rejecting the start pose; ``before()`` runs first (e.g. to hold the match)."""
    from lidarloc.core.matching.outcome import S2MOutcome

    def match(scan, pose, level=False):
        if before is not None:
            before()
        return S2MOutcome(
            accepted=accepted,
            pose=np.asarray(pose),
            score=1.0 if accepted else 0.0,
            start_score=0.0 if accepted else 1.0,
            region=(0, 0, 1, 1),
            ms=1.0,
        )

    loc.s2m.matcher.match_local = match


# ---------------------------------------------------------------------------------- a small street (viewer)
class StreetSequence(Sequence):
    """A straight street with building façades, poles and a flat road, scanned from a car driving
    along it at 8 m/s, 10 Hz. Small and fast: tests of the viewer need a real map, not a big one."""

    name = "test-street"

    def __init__(self, n: int = 24, seed: int = 0):
        rng = np.random.default_rng(seed)
        self.n = n
        walls = []
        for side in (-1, 1):
            for x0 in np.arange(-20, 260, 14.0):  # façades with gaps and varying depth
                depth = rng.uniform(7, 11)
                h = rng.uniform(6, 15)
                xs = rng.uniform(x0, x0 + 11, 2500)
                zs = rng.uniform(-1.7, h - 1.7, 2500)
                walls.append(np.stack([xs, np.full_like(xs, side * depth), zs], 1))
        poles = []
        for x in np.arange(0, 250, 9.0):
            z = rng.uniform(-1.7, 3.5, 120)
            poles.append(np.stack([np.full_like(z, x), np.full_like(z, 5.5), z], 1))
        road = np.stack([rng.uniform(-20, 260, 40000), rng.uniform(-10, 10, 40000), np.full(40000, -1.73)], 1)
        self.world = np.concatenate(walls + poles + [road])
        t = np.arange(n) * 0.1
        x = 8.0 * t
        y = 0.8 * np.sin(x / 40.0)
        yaw = np.arctan2(0.8 / 40.0 * np.cos(x / 40.0), 1.0)
        self._poses = pose_matrix(x, y, np.zeros(n), yaw, np.zeros(n), np.zeros(n))
        self._t = t

    def __len__(self):
        return self.n

    def _read_scan(self, i):
        T = self._poses[i]
        local = transform_points(np.linalg.inv(T), self.world)
        r = np.linalg.norm(local, axis=1)
        local = local[(r > 2.5) & (r < 50)]
        rng = np.random.default_rng(i)
        local = local + rng.normal(0, 0.02, local.shape)
        return np.concatenate([local, np.ones((len(local), 1))], 1).astype(np.float32)

    def describe_scan(self, i):
        return f"test street scan {i}"

    @property
    def timestamps(self):
        return self._t

    @property
    def poses(self):
        return self._poses


def make_localizer(seq, cache_root, n_particles: int = 300, s2m_nice: int = 0, **settings):
    """A Localizer with the default configuration but ``n_particles`` particles and the S2M
    process's replay-clock nice value ``s2m_nice`` (the PF's priority unless a test asks: the
    replay waits for every match, a niced S2M beside the other worker's tests crawls, and the
    priority never changes a replay's result); ``section__key=value`` sets any other setting."""
    from lidarloc.core.localizer import Localizer

    cfg = Config()
    cfg.pf.n_particles = n_particles
    cfg.s2m.replay_process_nice = s2m_nice
    for key, value in settings.items():
        section, name = key.split("__")
        setattr(getattr(cfg, section), name, value)
    return Localizer(seq, cfg, cache_root)


def browser_localizer(cache_root, n_scans: int = 60):
    """The localizer the browser test drives: long enough to pause mid-run.

    Its S2M process runs at the PF's priority: the replay clock waits for every match, and a
    niced S2M beside other busy processes (a loaded CI machine) gets a sliver of a core, so
    the run would crawl and the tests' timeouts would measure the machine, not the viewer.
    The priority never changes a replay result."""
    return make_localizer(StreetSequence(n=n_scans), cache_root, n_particles=1000, s2m_nice=0)


# The drive that maps the town: a run's scans are localized inside its map. Shorter than the
# default town's 1200 scans (a minute and a half to map) so that the map builds in seconds; the
# localizer works the same.
MAPPING_SCANS = 150


def short_town(scans: int):
    """The default town's first ``scans`` scans, mapped from a MAPPING_SCANS-scan drive."""
    from lidarloc.core.sequences.factory import SourceSpec, open_sequence

    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    return open_sequence(SourceSpec(scans=scans), cfg)


def assert_floor_keeps_the_weights(exact, floored, min_floored: int, margin: float = 800.0) -> None:
    """The floored log-likelihood gives the exact weights: particles within ``margin`` nats of the
    best are exact, the rest sit at the floor, and at least ``min_floored`` were floored."""
    import pytest

    w_exact = np.exp(exact - exact.max())
    w_floor = np.exp(floored - floored.max())
    np.testing.assert_allclose(w_floor / w_floor.sum(), w_exact / w_exact.sum(), rtol=1e-9, atol=1e-300)
    kept = exact > exact.max() - margin
    np.testing.assert_allclose(floored[kept], exact[kept], rtol=1e-9)
    assert np.all(floored[~kept] == pytest.approx(exact.max() - margin, rel=1e-9))
    assert (~kept).sum() > min_floored  # the floor did apply


def cache_with(entry: Path, cache: Path) -> Path:
    """``cache``, a cache of its own holding a copy of one map ``entry`` of another cache (the
    session's) and nothing else: a test of what a command puts in its cache starts there without
    building the map again."""
    import shutil

    shutil.copytree(entry, cache / entry.name)
    return cache


def record_run(out: Path, cache_root: Path, seed: int = 0, scans: int = 14) -> dict:
    """A recorded run of the short town, made as ``lidarloc run`` makes it (summary.json, scans.csv,
    recording/); its summary."""
    import io

    from lidarloc.app.headless import run_headless
    from lidarloc.core.sequences.factory import SourceSpec
    from rich.console import Console

    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    cfg.pf.n_particles = 300
    cfg.s2m.replay_process_nice = 0  # the replay waits for every match: a niced S2M crawls beside busy processes
    cfg.seed = seed
    summary, interrupted = run_headless(
        SourceSpec(scans=scans), cfg, out, cache_root, console=Console(file=io.StringIO())
    )
    assert not interrupted and (out / "recording").is_dir()
    return summary


def viewer_options(command: str, args: list[str], monkeypatch) -> dict:
    """The keyword options ``lidarloc <command> <args>`` hands to the viewer's server (which is not
    started: a stand-in records what it was given)."""
    from lidarloc.app import cli
    from lidarloc.app.viewer import serve as serve_module
    from typer.testing import CliRunner

    seen: dict = {}

    def fake(spec, cfg, **kwargs):
        seen.update(kwargs)

    monkeypatch.setattr(serve_module, "serve_until_interrupted", fake)
    result = CliRunner().invoke(cli.app, [command, *args])
    assert result.exit_code == 0, result.output
    return seen
