"""bench/run_all.py: finds the bench scripts, runs them and regenerates the benchmarks file,
refreshing only the sections asked for (issue 28)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def run_all() -> ModuleType:
    spec = importlib.util.spec_from_file_location("run_all", ROOT / "bench" / "run_all.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["run_all"] = mod
    spec.loader.exec_module(mod)
    return mod


def _bench(d: Path, name: str, body: str, doc: str, settings: str = "") -> None:
    (d / f"bench_{name}.py").write_text(f'"""{doc}\n\nMore text.\n"""\n{settings}\n{body}\n')


@pytest.fixture
def benches(tmp_path: Path) -> Path:
    d = tmp_path / "bench"
    d.mkdir()
    _bench(d, "alpha", "print('alpha says 1')", "Benchmark: the alpha figure.")
    _bench(d, "beta", "import sys\nprint('beta', sys.argv[1:])", "Beta timings.",
           'RUN_ALL = {"long": True, "args": ["--n", 3]}')
    _bench(d, "gamma", "print('plain')\nprint('<!-- markdown -->')\nprint('| a | b |')",
           "Gamma ``x`` (over\ntwo lines). Second sentence.")
    return d


def test_discovery_reads_titles_and_settings_without_importing(run_all: ModuleType,
                                                               benches: Path) -> None:
    found = {b.name: b for b in run_all.discover(benches, with_suite=False)}
    assert sorted(found) == ["alpha", "beta", "gamma"]
    assert found["alpha"].title == "The alpha figure" and not found["alpha"].long
    assert found["beta"].long and found["beta"].command[-2:] == ("--n", "3")
    assert found["gamma"].title == "Gamma `x` (over two lines)"
    names = [b.name for b in run_all.discover(benches)]
    assert names[-1] == "suite" and run_all.discover(benches)[-1].long
    # long ones only when named or with --long
    todo = run_all.choose(list(found.values()), [], [], False)
    assert [b.name for b in todo] == ["alpha", "gamma"]
    assert [b.name for b in run_all.choose(list(found.values()), [], ["gamma"], True)] == [
        "alpha", "beta"]
    with pytest.raises(SystemExit, match="unknown bench"):
        run_all.choose(list(found.values()), ["delta"], [], False)


def test_regenerates_and_only_refreshes_the_named_section(run_all: ModuleType, benches: Path,
                                                          tmp_path: Path) -> None:
    out = tmp_path / "benchmarks.md"
    common = ["--bench-dir", str(benches), "--out", str(out), "--no-suite"]
    assert run_all.main(common) == 0
    text = out.read_text()
    assert text.startswith("# Benchmarks\n")
    for line in ("\nMachine: ", "\nLast run of every default section: ",
                 "; load average (1 / 5 / 15 min) before ", "Sections in the last run: alpha, "
                 "gamma.", "Not run yet: beta."):
        assert line in text
    full_line = next(ln for ln in text.splitlines() if ln.startswith("Last run of every"))
    first = run_all.sections(text)
    assert list(first) == ["alpha", "beta", "gamma"]
    assert "## The alpha figure (`" in first["alpha"] and "alpha says 1" in first["alpha"]
    assert "exit status 0" in first["alpha"] and "Not run yet (long)" in first["beta"]
    # plain output as a text block, markdown after the marker as it is
    assert "```text\nplain\n```\n\n| a | b |\n<!-- /bench:gamma -->" in first["gamma"]

    _bench(benches, "alpha", "print('alpha says 2')", "Benchmark: the alpha figure.")
    assert run_all.main([*common, "--only", "beta"]) == 0
    second = run_all.sections(out.read_text())
    assert second["alpha"] == first["alpha"] and second["gamma"] == first["gamma"]
    assert "beta ['--n', '3']" in second["beta"]
    assert "Sections kept from earlier runs: alpha, gamma." in out.read_text()
    assert full_line in out.read_text() and "\nLast refreshed: beta, " in out.read_text()
    # a placeholder is not a measurement: written anew (here with the bench's new title)
    _bench(benches, "beta", "print('beta')", "Beta, renamed.", 'RUN_ALL = {"long": True}')
    assert run_all.main([*common, "--only", "gamma"]) == 0
    assert "Sections kept from earlier runs: alpha, beta." in out.read_text()
    (benches / "bench_delta.py").write_text('"""Delta."""\nRUN_ALL = {"long": True}\n')
    assert run_all.main([*common, "--only", "gamma"]) == 0
    assert "## Delta (`" in run_all.sections(out.read_text())["delta"]
    assert "Not run yet: delta." in out.read_text()
    second = run_all.sections(out.read_text())

    assert run_all.main([*common, "--only", "alpha", "--args", "alpha=--extra 1"]) == 0
    third = run_all.sections(out.read_text())
    assert "alpha says 2" in third["alpha"] and "--extra 1" in third["alpha"]
    assert third["beta"] == second["beta"]


def test_failing_and_hanging_benches_are_reported(run_all: ModuleType, tmp_path: Path) -> None:
    d = tmp_path / "bench"
    d.mkdir()
    _bench(d, "fails", "import sys\nprint('partial')\nsys.exit(3)", "Fails.")
    _bench(d, "hangs", "import time\nprint('started', flush=True)\ntime.sleep(60)", "Hangs.",
           'RUN_ALL = {"timeout_s": 1}')
    out = tmp_path / "b.md"
    assert run_all.main(["--bench-dir", str(d), "--out", str(out), "--no-suite"]) == 1
    s = run_all.sections(out.read_text())
    assert "exit status 3" in s["fails"] and "partial" in s["fails"]
    assert "killed after the timeout of 1 s" in s["hangs"] and "started" in s["hangs"]


def test_placeholders_are_written_anew(run_all: ModuleType, benches: Path) -> None:
    found = run_all.discover(benches, with_suite=False)
    beta = next(b for b in found if b.name == "beta")
    stale = run_all.placeholder(run_all.Bench(**{**beta.__dict__, "title": "Old title"}))
    text = run_all.assemble("# Benchmarks", found, {}, {"beta": stale})
    assert "## Beta timings (`" in run_all.sections(text)["beta"]
    assert "Old title" not in text
