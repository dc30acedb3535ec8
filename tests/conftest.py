"""Test set-up: every test runs on llvm_ad_rgb unless it asks for cuda_ad_rgb."""

from __future__ import annotations

import pytest

import mi_shadowgs  # finds libLLVM, selects the variant
from mi_shadowgs import backend

backend.set_variant("llvm_ad_rgb")


def _share_the_cores() -> None:
    """Under pytest-xdist, each worker's Dr.Jit gets its share of the cores, so that the
    workers' thread pools do not contend for them."""
    import os

    import drjit as dr

    workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    if workers > 1:
        dr.set_thread_count(max(1, (os.cpu_count() or 1) // workers))


_share_the_cores()

CUDA_AVAILABLE = backend.variant_available("cuda_ad_rgb")
CUDA_SKIP_REASON = (
    "cuda_ad_rgb needs an NVIDIA GPU and its driver; this machine has none, "
    "so the CUDA path is checked only on a GPU machine (see RESULTS.md)"
)


def pytest_collection_modifyitems(config, items):
    if CUDA_AVAILABLE:
        return
    skip = pytest.mark.skip(reason=CUDA_SKIP_REASON)
    for item in items:
        if "cuda" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def plugins():
    """mi_shadowgs's Mitsuba plugins registered, for a test that loads a scene naming them
    (they register when asked, not on import)."""
    return mi_shadowgs.register_plugins()


@pytest.fixture
def cuda_variant():
    """Switch to cuda_ad_rgb for one test, then back to llvm_ad_rgb."""
    backend.set_variant("cuda_ad_rgb")
    try:
        yield
    finally:
        backend.set_variant("llvm_ad_rgb")


FEW_VIEWS = "training view(s); the method needs at least"


def without_few_views_warning(err: str) -> str:
    """stderr without the too-few-training-views warning, which the tests' small datasets
    (8 views) rightly get; for tests that check the exact message of a command."""
    return "\n".join(ln for ln in err.splitlines() if FEW_VIEWS not in ln)


@pytest.fixture
def someone_elses_folder(tmp_path):
    """A folder holding a file no command of ours wrote (``todo.txt``): what an ``--out``
    must never be written into; check it with ``untouched``."""
    folder = tmp_path / "notes"
    folder.mkdir()
    (folder / "todo.txt").write_text("mine")
    return folder


@pytest.fixture
def tiny_presets(monkeypatch):
    """The test-tiny preset in every stage's table, for one test."""
    import tiny_cli

    for table, config in tiny_cli.presets():
        monkeypatch.setitem(table, tiny_cli.TINY, config)


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory):
    """``BASE/data`` (the default scene) and ``BASE/run`` (the method on it), at the test-tiny
    preset, made once in this process; tests only read them (with ``tiny_presets``). Its
    lights stay directional (``lamps=off``): at 24 px stage 4 takes a light for a lamp in
    some runs and not in others, and the tests that read the run would take other paths
    from run to run (the lamps have tests of their own)."""
    import tiny_cli
    from tiny_cli import TINY

    from mi_shadowgs import cli
    from mi_shadowgs.scenes import scene_path

    with pytest.MonkeyPatch.context() as mp:
        for table, config in tiny_cli.presets():
            mp.setitem(table, TINY, config)
        base = tmp_path_factory.mktemp("tiny_run")
        assert cli.main(["generate", str(scene_path("default")), "--out", str(base / "data"),
                         "--preset", TINY, "--no-progress"]) == 0
        assert cli.main(["run", str(base / "data"), "--out", str(base / "run"), "--preset",
                         TINY, "--no-progress", "--set", "material.lamps=off"]) == 0
    return base


@pytest.fixture
def one_thread():
    """Dr.Jit on one thread for one test: its float atomics then add in a fixed order, so
    two runs are bit-identical (see test_kill.py)."""
    import drjit as dr

    threads = dr.thread_count()
    dr.set_thread_count(1)
    yield
    dr.set_thread_count(threads)


def exits_2(main, argv, capsys) -> str:
    """stderr of ``main(argv)``, which must exit 2."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2, err
    return err


def untouched(folder) -> bool:
    """``someone_elses_folder`` as it was made."""
    return [p.name for p in folder.iterdir()] == ["todo.txt"] and \
        (folder / "todo.txt").read_text() == "mine"


def signal_on_call(monkeypatch, module, name: str, call: int, signum: int) -> None:
    """Send this process ``signum`` when ``module.name`` is called the ``call``-th time
    (before it runs), as a Ctrl-C (SIGINT) or a ``kill`` (SIGTERM) there would."""
    import os

    real, calls = getattr(module, name), []

    def sending(*args, **kwargs):
        calls.append(1)
        if len(calls) == call:
            os.kill(os.getpid(), signum)
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, sending)

