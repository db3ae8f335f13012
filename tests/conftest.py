"""Fixtures shared by several test files: the real KITTI data (skipped where it is absent), one
cache directory for the session, and worlds that take a while to build."""

import os
from pathlib import Path

import numpy as np
import pytest

# The recordings of the real drive (bags, a .pcd folder, TUM truth) are session fixtures of
# tests/bagfixtures.py, registered here once: a fixture imported into several test modules is
# a fixture of each of them, built again for every module that imports it.
from bagfixtures import kitti_drive, kitti_recordings  # noqa: F401

REPO = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------- pyright
# pyright over the repository takes about a minute of one core, in a process of its own: when its
# test is selected, it starts as soon as the tests are collected and runs beside them, and its
# test waits for its answer (tests/test_code_quality.py).
_pyright: dict = {}


def pytest_collection_finish(session):
    from helpers import PYRIGHT_TEST, start_pyright

    opt = session.config.option
    if os.environ.get("PYTEST_XDIST_WORKER"):  # every worker collects every test: its own worker starts it
        return
    if opt.collectonly or getattr(opt, "setuponly", False) or getattr(opt, "setupplan", False):
        return
    if any(item.nodeid.endswith(PYRIGHT_TEST) for item in session.items):
        _pyright["run"] = start_pyright()


def pytest_sessionfinish(session):
    run = _pyright.pop("run", None)
    if not isinstance(run, str) and run is not None:  # ended, if its test did not wait for it
        run.stop()


# ------------------------------------------------------------------------------- two workers
# `./run test` runs the suite on two pytest-xdist workers (--dist loadfile). A test file stays on
# one worker (its module fixtures are built once), and the files that share one of the slowest
# session fixtures (SHARED_FIXTURES) go to the same worker, which builds it once. The scheduler
# groups by file path because a test's id is all the scheduler sees (xdist's own `xdist_group`
# marks rename test ids, which pytest ≥ 9 no longer lets a plugin do: the marks were ignored).

#: The files that share one of the slowest session fixtures, by that fixture: they run on one
#: worker, which builds it once (the default town's 1200-scan map, ~40 s; the real drive written
#: as every recording kind, ~30 s; a local Ray cluster, ~20 s to start; the town's 40-scan run,
#: ~25 s). Two fixtures that share a file share their worker too.
SHARED_FIXTURES = {
    "default_town_cache": ("test_town_unchanged.py", "test_odometry_lag_bench.py"),
    "kitti_recordings": ("test_own_data.py", "test_rosbag.py", "test_scan_folder.py", "test_examples.py"),
    "recorded_town_run_40": ("test_examples.py", "test_branch.py"),
    "ray_local": ("test_bench.py", "test_shards.py", "test_sweep.py", "test_tune.py"),
}


def _shared_files() -> dict[str, str]:
    """Each file of SHARED_FIXTURES → its group, named after a fixture of it: the files of two
    fixtures that share a file are one group."""
    group: dict[str, str] = {}
    for fixture, names in SHARED_FIXTURES.items():
        paths = [f"tests/{name}" for name in names]
        joined = {group[p] for p in paths if p in group}  # the groups this fixture's files are in
        name = next((group[p] for p in paths if p in group), fixture)
        group = {p: name if g in joined else g for p, g in group.items()} | dict.fromkeys(paths, name)
    return group


SHARED_FILES = _shared_files()
SHARED_PATHS = {fixture: {f"tests/{name}" for name in names} for fixture, names in SHARED_FIXTURES.items()}

#: The files of the browser tests (``*_browser.py``, and these others that hold one) run one after
#: another on one worker: two headless Chromiums drawing in software at once would each get half
#: the cores their timeouts allow for.
BROWSER_GROUP = "browser"
BROWSER_FILES = ("tests/test_viewer_token.py",)

#: The longest groups of files, longest first (seconds of tests on a 2-core machine, roughly):
#: each starts before every shorter one, so that no long group starts last and keeps one worker
#: busy while the other has nothing left. The groups not named here follow in collection order.
LONGEST_FIRST = {
    BROWSER_GROUP: 380,
    "kitti_recordings": 320,
    "ray_local": 130,
    "tests/test_code_quality.py": 85,
    "tests/test_city_bench.py": 70,
    "tests/test_integrity.py": 70,
    "default_town_cache": 65,
    "tests/test_localizer.py": 60,
    "tests/test_clients.py": 60,
}


def scheduling_group(nodeid: str) -> str:
    """The group a test runs in: its file's, or the shared fixture's or the browser tests'."""
    path = nodeid.split("::", 1)[0]
    if path.endswith("_browser.py") or path in BROWSER_FILES:
        return BROWSER_GROUP
    return SHARED_FILES.get(path, path)


def pytest_xdist_make_scheduler(config, log):
    if config.getvalue("dist") not in ("loadfile", "loadgroup"):
        return None
    from xdist.scheduler import LoadFileScheduling

    class FileScheduling(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return scheduling_group(nodeid)

        def _assign_work_unit(self, node) -> None:
            # the longest group still waiting goes next (the base class takes the first)
            longest = max(self.workqueue, key=lambda group: LONGEST_FIRST.get(group, 0))
            self.workqueue.move_to_end(longest, last=False)
            super()._assign_work_unit(node)

    return FileScheduling(config, log)


def pytest_collection_modifyitems(config, items):
    # A test that uses a shared slow fixture from a file the scheduler does not know would build
    # it again on the other worker: say so at collection, where it is cheap to fix.
    for item in items:
        path = item.nodeid.split("::", 1)[0]
        if item.get_closest_marker("browser") and scheduling_group(item.nodeid) != BROWSER_GROUP:
            raise pytest.UsageError(f"{path} holds a browser test: add the file to BROWSER_FILES in tests/conftest.py")
        for fixture in SHARED_FIXTURES:
            if fixture in getattr(item, "fixturenames", ()) and path not in SHARED_PATHS[fixture]:
                raise pytest.UsageError(f"{path} uses {fixture}: add the file to SHARED_FIXTURES in tests/conftest.py")


@pytest.fixture(scope="session")
def pyright_run():
    """pyright's process over the repository (started at collection, or now), or why it cannot run."""
    from helpers import start_pyright

    if "run" not in _pyright:
        _pyright["run"] = start_pyright()
    return _pyright["run"]


def shared_data_dir() -> Path | None:
    """The real KITTI data: $LIDARLOC_DATA, else ../shared/data beside the project."""
    env = os.environ.get("LIDARLOC_DATA")
    path = Path(env) if env else REPO.parent / "shared" / "data"
    return path if path.is_dir() else None


@pytest.fixture(scope="session")
def shared_data() -> Path:
    path = shared_data_dir()
    if path is None:
        pytest.skip("real KITTI data not found (../shared/data or $LIDARLOC_DATA); licence keeps it out of the repo")
    return path


@pytest.fixture(scope="session")
def kitti_raw_dir(shared_data) -> Path:
    path = shared_data / "kitti_raw"
    if not (path / "2011_09_26" / "2011_09_26_drive_0013_sync").is_dir():
        pytest.skip(f"KITTI raw drive 0013 not found under {path}")
    return path


@pytest.fixture(scope="session")
def kitti_raw_seq(kitti_raw_dir):
    from lidarloc.core.sequences.kitti_raw import KittiRaw

    return KittiRaw(kitti_raw_dir, "2011_09_26", "0013")


@pytest.fixture(scope="session")
def kitti_raw_points(kitti_raw_seq):
    """Drive 0013's prior map points: all 100 scans fused with their poses (the paper's protocol),
    without the road-removed BEV copy (normal estimation: most of the build time)."""
    from lidarloc.core.config import MapConfig
    from lidarloc.core.maps.mapping import build_prior_map

    return build_prior_map(kitti_raw_seq, MapConfig(), road_removal=False).points


@pytest.fixture(scope="session")
def kitti_raw_map(kitti_raw_seq, kitti_raw_points):
    """Drive 0013's prior map (kitti_raw_points) and its lookup table, built once: (sequence,
    prior map, lookup table)."""
    from lidarloc.core.config import MapConfig
    from lidarloc.core.maps.lookup import LookupTable
    from lidarloc.core.maps.mapping import PriorMap

    voxel = MapConfig().voxel_size
    prior = PriorMap(points=kitti_raw_points, points_bev=np.zeros((0, 3), np.float32), voxel_size=voxel)
    return kitti_raw_seq, prior, LookupTable.build(prior.points, 0.25, 5.0)


@pytest.fixture(scope="session")
def drive_maps(kitti_raw_points, tmp_path_factory) -> dict:
    """The drive's whole map (kitti_raw_points) as a .pcd in the drive's frame ("local"), and the
    same map shifted by UTM_SHIFT ("utm"): a user's map file."""
    from helpers import UTM_SHIFT
    from lidarloc.core.maps.mapfile_write import write_map

    root = tmp_path_factory.mktemp("maps")
    write_map(root / "map.pcd", kitti_raw_points)
    write_map(root / "map_utm.pcd", kitti_raw_points, origin=UTM_SHIFT)
    return {"local": root / "map.pcd", "utm": root / "map_utm.pcd"}


@pytest.fixture(scope="session")
def cache_root(tmp_path_factory) -> Path:
    """One map cache for the session: sources share it (entries are keyed by source and
    parameters), so a map built by one test file is not built again by the next."""
    return tmp_path_factory.mktemp("cache")


@pytest.fixture(scope="session")
def town_cache(cache_root, tmp_path_factory) -> Path:
    """The session's cache holding the short town's world (the map of helpers.MAPPING_SCANS
    mapping scans, its lookup table, pyramid and place index), put there by a 2-scan run: the
    tests that start ``lidarloc`` on the short town in a child process find it built."""
    from helpers import record_run

    record_run(tmp_path_factory.mktemp("warm") / "run", cache_root, scans=2)
    return cache_root


@pytest.fixture(scope="session")
def town_map_entry(town_cache) -> Path:
    """The short town's map entry in the session's cache (a directory): copied into a cache of a
    test's own (helpers.cache_with), it spares that test the map's build, not its own entries."""
    from helpers import MAPPING_SCANS, short_town
    from lidarloc.core.config import Config
    from lidarloc.core.maps.mapping import map_cache_dir

    entry = map_cache_dir(short_town(MAPPING_SCANS).map_source, Config().map, town_cache)
    assert (entry / "meta.json").is_file(), entry
    return entry


@pytest.fixture(scope="session")
def default_town():
    """The default town and its drive (``--town-seed 0``, the default configuration), made once:
    a few seconds of generation that every test file of the town's own shares."""
    from lidarloc.core.config import TownConfig
    from lidarloc.core.sim.town import TownSequence

    return TownSequence.from_config(TownConfig(), seed=0)


@pytest.fixture(scope="session")
def default_town_cache(default_town, cache_root) -> Path:
    """The session's cache holding the default town's prior map (its 1200-scan mapping drive,
    the slowest map of the suite to build): built once, for the test that checks it is unchanged
    and the benchmarks that run on the default town."""
    from lidarloc.core.config import Config
    from lidarloc.core.maps.mapping import load_or_build_map

    load_or_build_map(default_town.map_source, Config().map, cache_root)
    return cache_root


@pytest.fixture(scope="session")
def recorded_town_run(cache_root, tmp_path_factory):
    """A recorded 14-scan run of the short town, made as ``lidarloc run`` makes it, shared by the
    tests that read a run's files back (exports, evo): (folder, summary)."""
    from helpers import record_run

    d = tmp_path_factory.mktemp("recorded") / "run"
    return d, record_run(d, cache_root, scans=14)


@pytest.fixture(scope="session")
def recorded_town_run_40(cache_root, tmp_path_factory) -> Path:
    """A recorded replay-clock run of the short town's first 40 scans with the default
    configuration (S2M on, the default particle count) but its S2M process at the PF's priority
    (the replay waits for every match, and a niced S2M beside busy processes crawls; the priority
    never changes the result), made as ``lidarloc run`` makes it: its folder. The branching tests
    branch it, the examples plot and branch it; none changes it."""
    from helpers import MAPPING_SCANS
    from lidarloc.app.headless import run_headless
    from lidarloc.core.config import Config
    from lidarloc.core.sequences.factory import SourceSpec
    from rich.console import Console

    cfg = Config()
    cfg.town.n_scans = MAPPING_SCANS
    cfg.s2m.replay_process_nice = 0
    out = tmp_path_factory.mktemp("original") / "run"
    summary, interrupted = run_headless(
        SourceSpec(scans=40), cfg, out, cache_root=cache_root, console=Console(stderr=True, quiet=True)
    )
    assert not interrupted and summary["s2m_landed"] > 5
    return out


@pytest.fixture(scope="session")
def toy_world():
    """The particle filter's toy world (helpers.toy_map) and its 0.25 m / 5 m lookup table."""
    from helpers import toy_map
    from lidarloc.core.maps.lookup import LookupTable

    pts = toy_map()
    return pts, LookupTable.build(pts, 0.25, 5.0)


@pytest.fixture(scope="module")
def browser():
    """Headless Chromium through Playwright (the browser tests skip without either)."""
    from browser import CHROMIUM, CHROMIUM_ARGS

    if not CHROMIUM.exists():
        pytest.skip("/usr/bin/chromium not found (apt-get install -y chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="Python Playwright not installed")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(autouse=True)
def _close_browser_pages(request):
    """After a browser test, passed or failed, its pages close: a page a failed test left open
    goes on drawing its scene in software WebGL and takes a core from the tests after it."""
    yield
    if "browser" in request.fixturenames:
        for context in list(request.getfixturevalue("browser").contexts):
            try:
                context.close()
            except Exception:  # the browser went away with its test: nothing left to close
                pass


@pytest.fixture(scope="module")
def street():
    """The small synthetic street the viewer tests drive."""
    from helpers import StreetSequence

    return StreetSequence()


@pytest.fixture
def viewer(street, cache_root):
    """A paused viewer on the street, on a free port."""
    from helpers import make_localizer
    from lidarloc.app.viewer.serve import serve

    loc = make_localizer(street, cache_root)
    handle = serve(loc, port=0, autoplay=False)
    yield handle
    handle.stop()
    loc.close()
