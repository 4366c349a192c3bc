"""Run the bench scripts and regenerate docs/benchmarks.md from their output (issue 28).

Every ``bench/bench_*.py`` is found by name and run as its own process from the repository
root with this Python; its standard output becomes its section of docs/benchmarks.md, under
the first line of its docstring, with the command, its wall and CPU time, the exit status,
the commit and the load average before and after. A bench prints plain text (shown as a
text block) or, after a line ``<!-- markdown -->``, markdown that is inserted as it is.
The file starts with a header: date, machine, commit, load before and after the whole run.

A bench may declare how it is run with a literal at module level (read, not imported)::

    RUN_ALL = {"args": ["--quick"], "long": True, "timeout_s": 1800}

``long`` benches (and ``manual`` ones, which need arguments only a person can give) run
only when named with ``--only`` (or with ``--long``); a section that is not run keeps what
the file already holds for it. ``suite`` (the whole test suite) is such a long section.

Run from the repository root::

    .venv/bin/python bench/run_all.py                  # every bench but the long ones
    .venv/bin/python bench/run_all.py --only compensation --only kinematics
    .venv/bin/python bench/run_all.py --long --skip station
    .venv/bin/python bench/run_all.py --list
"""

from __future__ import annotations

import argparse
import ast
import os
import re
import resource
import shlex
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH_DIR = Path(__file__).resolve().parent
OUT = ROOT / "docs" / "benchmarks.md"
HISTORY = "docs/benchmarks-history.md"
MARKDOWN = "<!-- markdown -->"
_PLACEHOLDER = "Not run yet"
_BEGIN = re.compile(r"^<!-- bench:([\w.-]+) -->$", re.M)

# How the benches already in bench/ are run (a bench's own RUN_ALL literal overrides this).
KNOWN: dict[str, dict[str, object]] = {
    "api_flood": {"long": True},
    "auto": {"long": True},
    "compensation_ab": {"manual": "needs --against SRC, the src directory of the reference"},
    "coverage": {"long": True},
    "design": {"long": True},
    "fit": {"long": True},
    "orientation": {"long": True},
    "sigma": {"long": True},
    "station": {"long": True},
}
SUITE_TITLE = "The whole test suite (`python -m pytest`, the configured workers)"
SUITE_COMMAND = ("-m", "pytest", "-q", "-p", "no:randomly")


@dataclass(frozen=True)
class Bench:
    """One section: a bench script (or the test suite) and how it is run."""

    name: str
    title: str
    command: tuple[str, ...]                    # arguments after the Python executable
    source: str                                 # what the heading names, e.g. bench/x.py
    long: bool = False
    manual: str | None = None
    timeout_s: float = 1800.0
    tail: int | None = None                     # keep only the last lines of the output


@dataclass
class Result:
    """What one run of a bench gave."""

    stdout: str
    status: int | None                          # None: killed on the timeout
    wall_s: float
    cpu_s: float
    load_before: float
    load_after: float
    started: str
    commit: str
    extra: dict[str, str] = field(default_factory=dict)


def _literal_settings(tree: ast.Module) -> dict[str, object]:
    for node in tree.body:
        if (isinstance(node, ast.Assign) and len(node.targets) == 1
                and isinstance(node.targets[0], ast.Name) and node.targets[0].id == "RUN_ALL"):
            value = ast.literal_eval(node.value)
            if not isinstance(value, dict):
                raise ValueError("RUN_ALL must be a dict literal")
            return value
    return {}


def _bench(name: str, title: str, command: tuple[str, ...], source: str,
           conf: dict[str, object]) -> Bench:
    manual, tail = conf.get("manual"), conf.get("tail")
    timeout = conf.get("timeout_s", 1800.0)
    args = conf.get("args", [])
    if not isinstance(args, list | tuple) or not isinstance(timeout, int | float):
        raise ValueError(f"{name}: RUN_ALL args must be a list, timeout_s a number")
    return Bench(name=name, title=title, command=(*command, *map(str, args)), source=source,
                 long=bool(conf.get("long", False)),
                 manual=None if manual is None else str(manual), timeout_s=float(timeout),
                 tail=None if not isinstance(tail, int) else tail)


def discover(bench_dir: Path = BENCH_DIR, *, with_suite: bool = True) -> list[Bench]:
    """The benches in ``bench_dir`` (``bench_*.py``, by name), then the test suite."""
    out = []
    for path in sorted(bench_dir.glob("bench_*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        # the docstring's first sentence (it may run over several lines)
        para = (ast.get_docstring(tree) or path.stem).strip().split("\n\n")[0]
        doc = re.split(r"(?<=\.)\s", " ".join(para.split()) + " ")[0]
        title = re.sub(r"^Benchmark:\s*", "", doc.strip()).rstrip(".").replace("``", "`")
        name = path.stem.removeprefix("bench_")
        rel = str(path.relative_to(ROOT) if path.is_relative_to(ROOT) else path)
        out.append(_bench(name, title[:1].upper() + title[1:], (rel,), rel,
                          {**KNOWN.get(name, {}), **_literal_settings(tree)}))
    if with_suite:
        out.append(_bench("suite", SUITE_TITLE, SUITE_COMMAND, "tests/",
                          {"long": True, "tail": 15, "timeout_s": 3600}))
    return out


def _commit() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, check=True,
                             capture_output=True, text=True, timeout=30).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=ROOT, capture_output=True, text=True, timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return sha + (" with uncommitted changes" if dirty.strip() else "")


def _now() -> str:
    return time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())


def run(bench: Bench, *, extra_args: tuple[str, ...] = (), commit: str | None = None
        ) -> Result:
    """Run ``bench`` in its own process group from the repository root; on the timeout the
    whole group is killed."""
    cmd = [sys.executable, *bench.command, *extra_args]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    load0 = os.getloadavg()[0]
    started = _now()
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        out, _ = proc.communicate(timeout=bench.timeout_s)
        status: int | None = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, _ = proc.communicate()
        status = None
    wall = time.perf_counter() - t0
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    return Result(stdout=out, status=status, wall_s=wall, cpu_s=cpu, load_before=load0,
                  load_after=os.getloadavg()[0], started=started,
                  commit=commit if commit is not None else _commit())


def render(bench: Bench, result: Result, *, extra_args: tuple[str, ...] = ()) -> str:
    """The markdown section of one run, between its markers."""
    cmd = shlex.join(["python", *bench.command, *extra_args])
    status = ("killed after the timeout of " f"{bench.timeout_s:.0f} s" if result.status is None
              else f"exit status {result.status}")
    lines = result.stdout.rstrip("\n").splitlines()
    text, md = lines, []
    if MARKDOWN in lines:
        k = lines.index(MARKDOWN)
        text, md = lines[:k], lines[k + 1:]
    if bench.tail is not None and len(text) > bench.tail:
        text = [f"[... {len(text) - bench.tail} lines left out]", *text[-bench.tail:]]
    body = [f"Run {result.started}, commit {result.commit}: `{cmd}`; wall "
            f"{result.wall_s:.1f} s, CPU {result.cpu_s:.1f} s (the process and its children), "
            f"{status}; load average {result.load_before:.2f} before, "
            f"{result.load_after:.2f} after."]
    if text:
        body += ["", "```text", *text, "```"]
    if md:
        body += ["", *md]
    return _wrap(bench, "\n".join(body))


def placeholder(bench: Bench) -> str:
    """Section of a bench that has not been run into this file yet."""
    why = f"manual ({bench.manual})" if bench.manual else "long"
    return _wrap(bench, f"{_PLACEHOLDER} ({why}): `python bench/run_all.py --only {bench.name}`.")


def _wrap(bench: Bench, body: str) -> str:
    return (f"<!-- bench:{bench.name} -->\n## {bench.title} (`{bench.source}`)\n\n"
            f"{body.rstrip()}\n<!-- /bench:{bench.name} -->")


def sections(text: str) -> dict[str, str]:
    """The sections of a generated file by name, each with its markers."""
    out = {}
    for m in _BEGIN.finditer(text):
        name = m.group(1)
        end_marker = f"<!-- /bench:{name} -->"
        end = text.find(end_marker, m.end())
        if end < 0:
            raise ValueError(f"section {name!r} has no end marker")
        out[name] = text[m.start():end + len(end_marker)]
    return out


_FULL = "Last run of every default section: "
_PARTIAL = "Last refreshed: "


def header(*, started: str, finished: str, commit: str, machine: str, load_before: str,
           load_after: str, ran: list[str], kept: list[str], missing: list[str],
           partial: bool = False, old_head: str = "") -> str:
    """The file's first lines: what produced it, where and when.

    A ``partial`` run (``--only``) keeps the old header's lines about the last run of every
    default section and adds one line about itself.
    """
    run = (f"{started} to {finished}, commit {commit}; load average (1 / 5 / 15 min) "
           f"before {load_before}, after {load_after}")
    lines = [
        "# Benchmarks",
        "",
        "Generated by `bench/run_all.py` from the output of the scripts in `bench/`; do not "
        "edit by hand (rerun a section with `python bench/run_all.py --only NAME`). Each "
        "section states its own run: date, commit, command, times and load. Figures measured "
        f"before this file was generated are in [{Path(HISTORY).name}]({Path(HISTORY).name}).",
        "",
        f"Machine: {machine}.",
    ]
    full = [ln for ln in old_head.splitlines() if ln.startswith(_FULL)] if partial else []
    lines += full or ([f"{_FULL}{run}."] if not partial else [])
    if partial:
        lines.append(f"{_PARTIAL}{', '.join(ran) or 'none'}, {run}.")
    lines.append(f"Sections in the last run: {', '.join(ran) or 'none'}.")
    if kept:
        lines.append(f"Sections kept from earlier runs: {', '.join(kept)}.")
    if missing:
        lines.append(f"Not run yet: {', '.join(missing)}.")
    return "\n".join(lines)


def kept_and_missing(benches: list[Bench], fresh: dict[str, str], old: dict[str, str]
                     ) -> tuple[list[str], list[str]]:
    """Names of the sections taken from the old file, and of those never run."""
    rest = [b.name for b in benches if b.name not in fresh]
    kept = [n for n in rest if _measured(old.get(n))]
    return kept, [n for n in rest if n not in kept]


def assemble(head: str, benches: list[Bench], fresh: dict[str, str], old: dict[str, str]
             ) -> str:
    """The whole file: ``head``, then per bench its new section, else its old one, else a
    placeholder (sections of benches that no longer exist are dropped)."""
    parts = [head]
    for b in benches:
        parts.append(fresh.get(b.name) or _measured(old.get(b.name)) or placeholder(b))
    return "\n\n".join(parts) + "\n"


def _measured(section: str | None) -> str | None:
    """``section`` unless it is a placeholder (those are written anew)."""
    return None if section is None or _PLACEHOLDER in section else section


def _load() -> str:
    a, b, c = os.getloadavg()
    return f"{a:.2f} / {b:.2f} / {c:.2f}"


def choose(benches: list[Bench], only: list[str], skip: list[str], long: bool) -> list[Bench]:
    """The benches to run: the named ones, else all but long/manual (unless ``long``) and
    the skipped ones."""
    names = {b.name for b in benches}
    unknown = sorted(set(only + skip) - names)
    if unknown:
        raise SystemExit(f"unknown bench(es): {', '.join(unknown)} (known: "
                         f"{', '.join(sorted(names))})")
    if only:
        return [b for b in benches if b.name in only]
    return [b for b in benches
            if b.name not in skip and b.manual is None and (long or not b.long)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", action="append", default=[], metavar="NAME",
                    help="run only this bench (repeatable); the other sections are kept")
    ap.add_argument("--skip", action="append", default=[], metavar="NAME",
                    help="do not run this bench (repeatable); its section is kept")
    ap.add_argument("--long", action="store_true", help="also run the long benches")
    ap.add_argument("--args", action="append", default=[], metavar="NAME=ARGS",
                    help="extra arguments for one bench, e.g. compensation_ab='--against x'")
    ap.add_argument("--list", action="store_true", help="list the benches and exit")
    ap.add_argument("--out", type=Path, default=OUT, help="file to regenerate")
    ap.add_argument("--bench-dir", type=Path, default=BENCH_DIR, help=argparse.SUPPRESS)
    ap.add_argument("--no-suite", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    sys.path.insert(0, str(BENCH_DIR))
    from _machine import machine

    benches = discover(a.bench_dir, with_suite=not a.no_suite)
    if a.list:
        for b in benches:
            flag = "manual" if b.manual else "long" if b.long else ""
            print(f"{b.name:18s} {flag:6s} python {shlex.join(b.command)}")
        return 0
    extra: dict[str, tuple[str, ...]] = {}
    for item in a.args:
        name, _, rest = item.partition("=")
        extra[name] = tuple(shlex.split(rest))
    todo = choose(benches, a.only, a.skip, a.long)
    old_text = a.out.read_text(encoding="utf-8") if a.out.exists() else ""
    old = sections(old_text)
    old_head = old_text.split("<!-- bench:", 1)[0]
    commit = _commit()
    started, load0 = _now(), _load()
    fresh: dict[str, str] = {}
    worst = 0
    for b in todo:
        print(f"[run_all] {b.name}: python {shlex.join(b.command + extra.get(b.name, ()))}",
              flush=True)
        res = run(b, extra_args=extra.get(b.name, ()), commit=commit)
        fresh[b.name] = render(b, res, extra_args=extra.get(b.name, ()))
        print(f"[run_all] {b.name}: {res.wall_s:.1f} s, status {res.status}", flush=True)
        worst = max(worst, 1 if res.status is None else min(res.status, 1))
        # written after every bench: an interrupted run keeps what it measured
        kept, missing = kept_and_missing(benches, fresh, old)
        head = header(started=started, finished=_now(), commit=commit, machine=machine(),
                      load_before=load0, load_after=_load(), ran=list(fresh), kept=kept,
                      missing=missing, partial=bool(a.only), old_head=old_head)
        a.out.write_text(assemble(head, benches, fresh, old), encoding="utf-8")
    return worst


if __name__ == "__main__":
    sys.exit(main())
