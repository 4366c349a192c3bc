"""Fuzzing every file format robocal reads: MODEL.json, PLAN.json, the daemon configuration
(TOML) and the measurement / joint / target CSVs. Random documents and valid documents with
one part replaced by random JSON are fed to the readers; each must either load or raise one
error of robocal's tree (``RobocalError``), never anything else.

Examples per test are weighted by the reader's cost and scaled by ``FUZZ_SCALE``: the
default 0.05 (about 520 inputs) keeps the suite quick; ``FUZZ_SCALE=1`` feeds 10,500 inputs
(``test_report_the_count`` prints the count, ``-s`` shows it).
"""

from __future__ import annotations

import contextlib
import copy
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from robocal._core.measurements import MeasurementSet, read_joints_csv
from robocal.compensation import CompensationTable
from robocal.compensation._targets import read_targets_csv
from robocal.daemon._plan import parse_plan
from robocal.daemon.config import config_errors, load_config
from robocal.errors import RobocalError
from robocal.kinematics import CalibratedModel, ErrorModelSpec, KinematicModel
from robocal.simulation import VirtualCell

SCALE = float(os.environ.get("FUZZ_SCALE", "0.05"))
WEIGHTS = {"model": 750, "plan": 750, "config": 2000, "csv": 1750}  # per test; 2 tests each
TOTAL = 2 * round(sum(WEIGHTS.values()) * SCALE)


def fuzz(kind: str) -> Any:
    return settings(max_examples=max(1, round(WEIGHTS[kind] * SCALE)), deadline=None,
                    derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.filter_too_much,
                                           HealthCheck.function_scoped_fixture])
COUNT: dict[str, int] = {}
#: The fuzz tests that ran to the end in this process (xdist may spread the module over workers
#: and pytest-randomly shuffles it, so the count is checked only where all of them ran first).
RAN: set[str] = set()
FUZZ_TESTS = {"test_model_json_mutated", "test_model_json_random", "test_plan_json_mutated",
              "test_plan_json_random", "test_config_mutated", "test_config_and_table_random",
              "test_csv_mutated", "test_csv_random"}


@pytest.fixture(autouse=True)
def _ran(request: pytest.FixtureRequest) -> Iterator[None]:
    yield
    RAN.add(request.node.originalname)

numbers = st.one_of(st.integers(-10**6, 10**6), st.integers(), st.floats(),
                    st.sampled_from([1e300, -1e308, 0.0, -0.0, 2**63, 10**5000 // 10**4990]))
leaves = st.one_of(st.none(), st.booleans(), numbers, st.text(max_size=20))
json_values = st.recursive(leaves, lambda kids: st.one_of(
    st.lists(kids, max_size=6), st.dictionaries(st.text(max_size=10), kids, max_size=6)),
    max_leaves=30)


def _count(fmt: str) -> None:
    COUNT[fmt] = COUNT.get(fmt, 0) + 1


def _mutate(doc: Any, data: st.DataObject) -> Any:
    """``doc`` with one randomly chosen subtree replaced by random JSON (or removed)."""
    doc = copy.deepcopy(doc)
    node = doc
    while True:
        keys = list(node) if isinstance(node, dict) else list(range(len(node)))
        if not keys:
            return doc
        k = data.draw(st.sampled_from(keys))
        child = node[k]
        if isinstance(child, dict | list) and child and data.draw(st.booleans()):
            node = child
            continue
        if isinstance(node, dict) and data.draw(st.integers(0, 9)) == 0:
            del node[k]
        else:
            node[k] = data.draw(json_values)
        return doc


def _must_load_or_refuse(fn: Any, *args: Any) -> None:
    with contextlib.suppress(RobocalError):
        fn(*args)


@pytest.fixture(scope="module")
def model_doc() -> dict[str, Any]:
    cell = VirtualCell.create("fanuc_lrmate200i", "constant", seed=1)
    const = KinematicModel(cell.robot, ErrorModelSpec.constant(cell.robot.dof),
                           cell.truth_model.T_ref)
    fb = CalibratedModel(const, cell.truth_model.transfer(cell.truth_params, const))
    cm = CalibratedModel(cell.truth_model, cell.truth_params, fallback=fb,
                         coverage=np.tile([[-1.5, 1.5]], (cell.robot.dof, 1)),
                         covariance=np.eye(cell.truth_model.size) * 1e-12)
    return cm.to_dict()


@pytest.fixture(scope="module")
def plan_doc(real_plan: dict[str, Any]) -> dict[str, Any]:
    return real_plan


@pytest.fixture(scope="module")
def real_plan() -> dict[str, Any]:
    from robocal.planning import plan_campaign

    plan = plan_campaign("fanuc_lrmate200i", "demo", count=12, model="constant", validation=2,
                         cpa=False, iso=False, seed=3, candidates=64)
    return json.loads(plan.to_json())


@pytest.fixture(scope="module")
def scratch() -> Any:
    with tempfile.TemporaryDirectory() as d:
        yield Path(d)


# --- MODEL.json ---------------------------------------------------------------------------------
@fuzz("model")
@given(data=st.data())
def test_model_json_mutated(model_doc, scratch, data):
    doc = _mutate(model_doc, data)
    _count("MODEL.json")
    _must_load_or_refuse(CalibratedModel.from_dict, doc)
    p = scratch / "MODEL.json"
    p.write_text(json.dumps(doc))
    _must_load_or_refuse(CalibratedModel.load, p)


@fuzz("model")
@given(text=st.one_of(st.text(max_size=200), json_values.map(json.dumps),
                      st.binary(max_size=200).map(lambda b: b.decode("latin-1"))))
def test_model_json_random(scratch, text):
    _count("MODEL.json")
    p = scratch / "MODEL.json"
    p.write_text(text, encoding="utf-8", errors="surrogatepass")
    _must_load_or_refuse(CalibratedModel.load, p)


# --- PLAN.json ----------------------------------------------------------------------------------
@fuzz("plan")
@given(data=st.data())
def test_plan_json_mutated(plan_doc, data):
    _count("PLAN.json")
    doc = _mutate(plan_doc, data)
    _must_load_or_refuse(parse_plan, doc)
    _must_load_or_refuse(lambda text: parse_plan(text, strict=False), json.dumps(doc))


@fuzz("plan")
@given(value=json_values)
def test_plan_json_random(value):
    _count("PLAN.json")
    _must_load_or_refuse(parse_plan, json.dumps(value))
    if isinstance(value, dict):
        _must_load_or_refuse(parse_plan, {"format": "robocal.plan/1", **value})


# --- configuration (TOML) and compensation tables ------------------------------------------------
_CONFIG = """data_dir = "state"
robot_description = "fanuc_lrmate200i"
[robot]
kind = "mock"
options = { robot = "fanuc_lrmate200i" }
[tracker]
kind = "mock"
[api]
tcp_port = 0
token_file = "tok"
[measurement]
samples = 4
[fit]
models = ["constant"]
select = "constant"
[limits]
speed_pct = 20.0
"""

toml_scalars = st.one_of(st.integers().map(str),
                         st.floats(allow_nan=False, allow_infinity=False).map(repr),
                         st.booleans().map(lambda b: str(b).lower()),
                         st.text(max_size=15).map(json.dumps),
                         st.just("[1, 2"), st.just('"\\u0000"'), st.just("{a = }"),
                         st.just("1e400"), st.just("nan"), st.just("[" * 50))


@fuzz("config")
@given(data=st.data())
def test_config_mutated(scratch, data):
    _count("config")
    lines = _CONFIG.splitlines()
    i = data.draw(st.integers(0, len(lines) - 1))
    how = data.draw(st.integers(0, 2))
    if how == 0 and "=" in lines[i]:
        lines[i] = lines[i].split("=", 1)[0] + "= " + data.draw(toml_scalars)
    elif how == 1:
        lines.insert(i, data.draw(st.text(max_size=30)).replace("\r", ""))
    else:
        lines[i] = data.draw(st.sampled_from(["[robot]", "[x.y]", "kind = 1", "a.b.c = 2",
                                              "[[fit]]", "bogus = true", ""]))
    p = scratch / "robocal.toml"
    p.write_bytes("\n".join(lines).encode("utf-8", "surrogatepass"))
    _must_load_or_refuse(load_config, p)
    assert isinstance(config_errors(p), list)


@fuzz("config")
@given(value=json_values, raw=st.binary(max_size=100))
def test_config_and_table_random(scratch, value, raw):
    _count("config")
    _count("table")
    p = scratch / "random.toml"
    p.write_bytes(raw)
    _must_load_or_refuse(load_config, p)
    t = scratch / "table.json"
    t.write_text(json.dumps(value))
    _must_load_or_refuse(CompensationTable.read, t)


# --- CSVs ----------------------------------------------------------------------------------------
_CSV = ("pose_id,q1,q2,q3,q4,q5,q6,x,y,z,sx,sy,sz\n"
        "P1,10,20,-10,5,30,15,1500.5,200.25,300,0.01,0.01,0.02\n"
        "P2,0,10,5,-5,20,0,1400,210,320,0.01,0.01,0.02\n")
cells = st.one_of(st.sampled_from(["", "nan", "inf", "1e300", "-1e308", "1,5", "x", '"', "1e5",
                                   "3601", "0x10", " 7 ", ";", "\x00"]),
                  st.floats().map(repr), st.text(max_size=8))


@fuzz("csv")
@given(data=st.data())
def test_csv_mutated(scratch, data):
    _count("CSV")
    rows = [r.split(",") for r in _CSV.splitlines()]
    for _ in range(data.draw(st.integers(1, 3))):
        r = data.draw(st.integers(0, len(rows) - 1))
        c = data.draw(st.integers(0, len(rows[r]) - 1))
        rows[r][c] = data.draw(cells)
    if data.draw(st.booleans()):
        rows[data.draw(st.integers(0, len(rows) - 1))].pop()
    text = "\n".join(",".join(r) for r in rows) + "\n"
    p = scratch / "meas.csv"
    p.write_bytes(text.encode("utf-8", "surrogatepass"))
    _must_load_or_refuse(MeasurementSet.read_csv, p)
    _must_load_or_refuse(read_joints_csv, p)
    _must_load_or_refuse(read_targets_csv, p)


@fuzz("csv")
@given(text=st.text(alphabet=st.sampled_from(list("q123xyzs_,;\n.-e9 \"\t")) | st.characters(),
                    max_size=300))
def test_csv_random(scratch, text):
    _count("CSV")
    p = scratch / "random.csv"
    p.write_bytes(text.encode("utf-8", "surrogatepass"))
    for reader in (MeasurementSet.read_csv, read_joints_csv, read_targets_csv):
        _must_load_or_refuse(reader, p)


def test_report_the_count():
    """Runs last in this module: the number of inputs fed to the readers above."""
    total = sum(COUNT.values())
    print(f"fuzz inputs: {total} ({COUNT})")
    if RAN >= FUZZ_TESTS:  # every fuzz test ran before this one, in this process
        assert total >= TOTAL
