"""The committed runs: one gzipped JSON record per run, read back as ``run``'s CSV reads."""

import gzip
import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from synthetic import write_run

from tamrm_experiments import cli
from tamrm_experiments.archive import (
    add_runs,
    archive_path,
    decode_run,
    encode_run,
    read_record,
)
from tamrm_experiments.configs import make_specs
from tamrm_experiments.load import load_runs
from tamrm_experiments.run import is_complete, run_paths
from tamrm_experiments.verdicts import run_metrics

floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
ints = st.integers(min_value=-(2**62), max_value=2**62)
columns = st.lists(st.sampled_from(["int64", "float64", "bool", "object"]), min_size=1, max_size=5)


@st.composite
def frames(draw):
    """A frame of the dtypes pandas.read_csv gives: ints, floats (nan and infinities
    included), booleans and text with missing values."""
    n = draw(st.integers(min_value=0, max_value=12))
    data = {}
    for i, dtype in enumerate(draw(columns)):
        if dtype == "int64":
            values = draw(st.lists(ints, min_size=n, max_size=n))
        elif dtype == "float64":
            values = draw(st.lists(floats, min_size=n, max_size=n))
        elif dtype == "bool":
            values = draw(st.lists(st.booleans(), min_size=n, max_size=n))
        else:
            text = st.one_of(st.text(max_size=5), st.just(math.nan))
            values = draw(st.lists(text, min_size=n, max_size=n))
        data[f"c{i}"] = pd.Series(values, dtype=dtype)
    return pd.DataFrame(data)


meta = st.dictionaries(
    st.text(max_size=4),
    st.one_of(st.integers(), st.text(max_size=4), st.booleans(), st.none()),
    max_size=4,
)


@settings(max_examples=150, deadline=None)
@given(frames(), meta)
def test_a_record_round_trips_value_for_value_and_byte_for_byte(df, sidecar):
    data = encode_run(sidecar, df)
    got_meta, got = decode_run(data)
    assert got_meta == sidecar
    assert list(got.columns) == list(df.columns)
    assert list(got.dtypes) == list(df.dtypes)
    for col in df.columns:
        want, have = df[col].tolist(), got[col].tolist()
        assert len(want) == len(have)
        for a, b in zip(want, have, strict=True):
            if isinstance(a, float) and math.isnan(a):
                assert isinstance(b, float) and math.isnan(b)
            else:
                assert a == b and type(a) is type(b)
    # Deterministic: the same run gives the same bytes, and the gzip header has no time.
    assert encode_run(sidecar, got) == data
    assert data[4:8] == b"\0\0\0\0"


def _finished_runs(root, seeds=2):
    specs = make_specs("quick", seeds=seeds, experiments=["maze"], variants=["clean"])
    for spec in specs:
        write_run(root, spec, [40 + 3 * spec.seed + len(spec.arm)] * spec.budget.episodes)
    return specs


def test_a_run_reads_the_same_from_its_csv_and_from_its_record(tmp_path):
    runs, archive = tmp_path / "runs", tmp_path / "archive"
    specs = _finished_runs(runs)
    # A CSV float that pandas parses with its own parser: kept as parsed.
    csv_path = run_paths(runs, specs[0])[0]
    text = csv_path.read_text().replace(",1.5,", ",0.1000000000000000055511151231257827,", 1)
    csv_path.write_text(text)
    summary = add_runs(runs, archive)
    assert len(summary.added) == len(specs) and not summary.conflicts
    from_csv, from_archive = load_runs(runs), load_runs(archive)
    assert [r.key for r in from_csv] == [r.key for r in from_archive]
    for a, b in zip(from_csv, from_archive, strict=True):
        assert a.meta == b.meta
        assert a.df.equals(b.df) and list(a.df.dtypes) == list(b.df.dtypes)
        assert run_metrics(a) == run_metrics(b)
    record = archive_path(archive, run_paths(runs, specs[0])[2].relative_to(runs))
    assert record.name == "seed0.json.gz"
    assert json.loads(gzip.decompress(record.read_bytes()))["meta"]["spec"]["arm"] == "plain"


def test_add_runs_adds_each_run_once_and_never_rewrites_one(tmp_path):
    runs, archive = tmp_path / "runs", tmp_path / "archive"
    specs = _finished_runs(runs, seeds=1)
    (runs / "invocations.jsonl").write_text('{"command": "a"}\n{"command": "b"}\n')
    # An unfinished run (no sidecar yet, or one without "complete") is not added.
    partial = run_paths(runs, replace(specs[0], seed=7))
    partial[0].parent.mkdir(parents=True, exist_ok=True)
    partial[1].write_text("episode,steps\n1,5\n")
    partial[2].write_text(json.dumps({"spec": specs[0].to_dict(), "complete": False}))
    first = add_runs(runs, archive)
    assert (len(first.added), first.unfinished, first.invocations) == (len(specs), 1, 2)
    before = {p: p.read_bytes() for p in archive.rglob("*.gz")}
    again = add_runs(runs, archive)
    assert (len(again.added), len(again.unchanged), again.invocations) == (0, len(specs), 0)
    # The same run finished again with other results: a conflict, the record kept.
    write_run(runs, specs[0], [99] * specs[0].budget.episodes)
    with open(runs / "invocations.jsonl", "a") as fh:
        fh.write('{"command": "c"}\n')
    third = add_runs(runs, archive)
    record = archive_path(archive, run_paths(runs, specs[0])[2].relative_to(runs))
    assert third.conflicts == [record]
    assert {p: p.read_bytes() for p in archive.rglob("*.gz")} == before
    assert (archive / "invocations.jsonl").read_text().splitlines() == [
        '{"command": "a"}',
        '{"command": "b"}',
        '{"command": "c"}',
    ]
    assert "conflict" in third.lines()[1] and str(record) in third.lines()[1]
    assert cli.main(["add-runs", "--runs", str(runs), "--to", str(archive)]) == 1


def test_the_grid_skips_the_runs_in_the_archive(tmp_path):
    runs, archive, scratch = tmp_path / "runs", tmp_path / "archive", tmp_path / "scratch"
    specs = _finished_runs(runs, seeds=1)
    add_runs(runs, archive)
    assert not is_complete(scratch, specs[0])
    assert is_complete(scratch, specs[0], archive)
    # A recorded run of other settings does not count.
    other = replace(specs[0], budget=replace(specs[0].budget, episodes=9))
    assert not is_complete(scratch, other, archive)


def test_a_damaged_or_doubled_run_is_an_error_naming_it(tmp_path):
    runs = tmp_path / "runs"
    specs = _finished_runs(runs, seeds=1)
    add_runs(runs, runs)  # the same runs recorded beside their CSVs
    with pytest.raises(ValueError, match="recorded twice"):
        load_runs(runs)
    archive = tmp_path / "archive"
    add_runs(runs, archive)
    record = next(archive.rglob("*.gz"))
    record.write_bytes(gzip.compress(b'{"format": "something else"}'))
    with pytest.raises(ValueError, match=re.escape(f"{record}: format 'something else'")):
        read_record(record)
    record.write_bytes(b"not gzip")
    with pytest.raises(ValueError, match="not a gzipped JSON run record"):
        load_runs(archive)
    bad = encode_run({"spec": specs[0].to_dict()}, pd.DataFrame({"a": [1, 2]}))
    record = json.loads(gzip.decompress(bad))
    record["rows"][1] = [1, 2]
    with pytest.raises(ValueError, match="rows of other lengths"):
        decode_run(gzip.compress(json.dumps(record).encode()), "x.json.gz")


def test_the_committed_records_read_back_as_finished_runs():
    root = Path(__file__).resolve().parents[2] / "docs" / "reproduction"
    records = sorted((root / "runs").rglob("seed*.json.gz"))
    assert records, "docs/reproduction/runs holds no run records"
    for path in records[:: max(1, len(records) // 25)]:
        meta, df = read_record(path)
        spec = meta["spec"]
        assert meta["complete"] and path.parts[-4:-1] == (
            spec["experiment"],
            spec["variant"],
            spec["arm"],
        )
        assert len(df) == meta["episodes"]
        assert int(np.asarray(df["steps"]).sum()) <= meta["total_steps"]
