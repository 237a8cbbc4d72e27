"""Integration tests through the `fusionlog` command line (DESIGN.md, "CLI" contract).

Most tests drive `fusionlog.cli:main` in-process with click's CliRunner (fast: no interpreter
start-up, no re-import of numpy/rerun). Whatever a user sees only from outside the process --
exit codes of the real console script, SIGINT, progress bars on a terminal versus a pipe,
--debug tracebacks, decoding by third-party tools -- goes through subprocesses.

Runs are small (a few hundred Monte Carlo runs, K = 10) so the whole file stays well under a
minute on two cores.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli, listing, ok, one_line_error

from fusionlog.compare import compare_summaries
from fusionlog.errors import FusionlogError
from fusionlog.io.mcap import McapFile
from fusionlog.io.rrd import read_recording

ROOT = Path(__file__).resolve().parents[1]
AJGL = ROOT / "pipeline" / "ajgl2009.toml"
HETERO = ROOT / "pipeline" / "heterogeneous.toml"
BIN = Path(sys.executable).parent
FUSIONLOG = str(BIN / "fusionlog") if (BIN / "fusionlog").exists() else shutil.which("fusionlog")
RERUN = str(BIN / "rerun") if (BIN / "rerun").exists() else shutil.which("rerun")
ENV = {**os.environ, "RERUN_ANALYTICS": "0"}
SMALL = ["--runs", "200", "--steps", "10"]
OUTPUTS = ("sensors.mcap", "estimates.mcap", "evaluation.rrd", "summary.json")
ARCHS = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "FBS"]

needs_fusionlog = pytest.mark.skipif(FUSIONLOG is None, reason="fusionlog console script missing")
needs_rerun = pytest.mark.skipif(RERUN is None, reason="rerun CLI missing")


# ------------------------------------------------------------------------------------------
# helpers
# ------------------------------------------------------------------------------------------


def run_proc(*args: str | os.PathLike[str], cwd: Path | None = None, **kw):
    """Run the real console script (or the rerun CLI if args[0] is RERUN)."""
    cmd = [str(a) for a in args]
    if cmd[0] not in (FUSIONLOG, RERUN):
        cmd = [FUSIONLOG, *cmd]
    return subprocess.run(
        cmd, capture_output=True, text=True, env=ENV, cwd=cwd, timeout=120, check=False, **kw
    )


def snapshot(paths) -> dict[str, tuple[int, bytes]]:
    return {str(p): (p.stat().st_mtime_ns, p.read_bytes()) for p in paths}


def all_arrays(path: Path) -> dict[str, np.ndarray]:
    """Every fusionlog topic of an MCAP file as arrays, via fusionlog's reader."""
    f = McapFile(path)
    data = f.read_all(sorted(f.topics))
    out: dict[str, np.ndarray] = {}
    for topic, v in data.items():
        if isinstance(v, tuple):
            out[topic + ":mean"], out[topic + ":cov"] = v
        else:
            out[topic] = v
    return out


def assert_same_arrays(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> None:
    assert a.keys() == b.keys()
    for k in a:
        assert a[k].shape == b[k].shape, k
        assert np.array_equal(a[k], b[k], equal_nan=True), k


def write_toml(path: Path, text: str) -> Path:
    path.write_text(textwrap.dedent(text))
    return path


@pytest.fixture(scope="module")
def ajgl_run(tmp_path_factory) -> Path:
    """One `fusionlog run` of the paper's scenario (200 runs, K = 10), shared read-only."""
    d = tmp_path_factory.mktemp("ajgl") / "out"
    res = ok("run", AJGL, "--out-dir", d, *SMALL)
    assert "CKF" in res.stdout
    return d


# ------------------------------------------------------------------------------------------
# run
# ------------------------------------------------------------------------------------------


def test_run_writes_all_outputs_and_prints_the_table(ajgl_run: Path) -> None:
    assert listing(ajgl_run) == sorted(OUTPUTS)  # and no temp file left behind
    summary = json.loads((ajgl_run / "summary.json").read_text())
    assert summary["scenario"] == "ajgl2009" and summary["seed"] == 2009
    assert summary["runs"] == 200 and summary["steps"] == 10
    assert list(summary["architectures"]) == ARCHS
    sens, est = McapFile(ajgl_run / "sensors.mcap"), McapFile(ajgl_run / "estimates.mcap")
    assert sorted(sens.topics) == ["/sensors/s1", "/sensors/s2", "/sensors/s3", "/truth"]
    assert sorted(est.topics) == sorted(f"/estimates/{a}" for a in ARCHS)
    assert sens.runs() == est.runs() == 200 and sens.steps() == est.steps() == 11
    rec = read_recording(ajgl_run / "evaluation.rrd")
    assert rec["summary"] == summary


def test_run_table_on_stdout(tmp_path: Path) -> None:
    res = ok("run", AJGL, "--out-dir", tmp_path / "o", "--runs", "50", "--steps", "5")
    lines = res.stdout.splitlines()
    assert lines[0] == "ajgl2009: M = 50 runs, K = 5, seed 2009"
    assert lines[1].split()[:3] == ["architecture", "MSE", "E[MSE]"]
    assert [ln.split()[0] for ln in lines[3 : 3 + len(ARCHS)]] == ARCHS
    assert res.stderr == ""


def test_run_refuses_to_overwrite_then_force(ajgl_run: Path, tmp_path: Path) -> None:
    d = tmp_path / "out"
    shutil.copytree(ajgl_run, d)  # copy2 keeps the old mtimes
    before = snapshot(d / n for n in OUTPUTS)
    res = cli("run", AJGL, "--out-dir", d, *SMALL)
    one_line_error(res, str(d / "sensors.mcap"), "exists", "--force")
    assert snapshot(d / n for n in OUTPUTS) == before
    assert listing(d) == sorted(OUTPUTS)

    ok("run", AJGL, "--out-dir", d, *SMALL, "--force")
    after = snapshot(d / n for n in OUTPUTS)
    assert all(after[k][0] != before[k][0] for k in before)  # every output rewritten
    assert listing(d) == sorted(OUTPUTS)
    # Same seed, same settings: the same results.
    a = json.loads((d / "summary.json").read_text())
    b = json.loads((ajgl_run / "summary.json").read_text())
    assert compare_summaries(a, b, rtol=0, atol=0) == []


def test_run_force_that_fails_leaves_the_old_outputs(ajgl_run: Path, tmp_path: Path, monkeypatch):
    """Outputs are staged and moved into place together: a failure in the last stage keeps the
    previous run's four files as they were (no new sensors next to old estimates), and no
    staging folder is left behind."""
    import fusionlog.stages.run as run_stage

    d = tmp_path / "out"
    shutil.copytree(ajgl_run, d)
    before = snapshot(d / n for n in OUTPUTS)
    before_bytes = {n: (d / n).read_bytes() for n in OUTPUTS}

    def fail(*args, **kwargs):
        raise FusionlogError("disk trouble while evaluating")

    monkeypatch.setattr(run_stage, "evaluate_into", fail)
    res = cli("run", AJGL, "--out-dir", d, "--runs", "30", "--steps", "4", "--force")
    one_line_error(res, "disk trouble")
    assert snapshot(d / n for n in OUTPUTS) == before
    assert {n: (d / n).read_bytes() for n in OUTPUTS} == before_bytes
    assert listing(d) == sorted(OUTPUTS)


def test_run_refuses_when_only_a_later_output_exists(tmp_path: Path) -> None:
    d = tmp_path / "out"
    d.mkdir()
    (d / "summary.json").write_text("{}")
    res = cli("run", AJGL, "--out-dir", d, *SMALL)
    one_line_error(res, str(d / "summary.json"), "exists")
    assert listing(d) == ["summary.json"]  # nothing simulated before refusing
    assert (d / "summary.json").read_text() == "{}"


def test_run_heterogeneous(tmp_path: Path) -> None:
    d = tmp_path / "het"
    res = ok("run", HETERO, "--out-dir", d, "--runs", "100", "--steps", "8")
    assert listing(d) == sorted(OUTPUTS)
    summary = json.loads((d / "summary.json").read_text())
    assert summary["scenario"] == "heterogeneous" and summary["steps"] == 8
    assert list(summary["architectures"]) == [*ARCHS, "AVG"]
    sens = McapFile(d / "sensors.mcap")
    dims = {t: sens.dim_of(t) for t in sens.topics}
    assert dims == {
        "/truth": 2,
        "/sensors/laser": 1,
        "/sensors/gnss": 2,
        "/sensors/odometer": 1,
        "/sensors/beacon": 1,
    }
    assert sens.times()[1] == 0.5  # dt = 0.5
    for a in ARCHS:
        assert math.isfinite(summary["architectures"][a]["mse"])
    assert "heterogeneous: M = 100 runs, K = 8" in res.stdout


def test_run_default_out_dir_is_recordings_name(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    ok("run", AJGL, "--runs", "20", "--steps", "3", "--arch", "CKF")
    assert listing(tmp_path / "recordings" / "ajgl2009") == sorted(OUTPUTS)


def test_run_with_arch_subset(tmp_path: Path) -> None:
    d = tmp_path / "o"
    ok("run", AJGL, "--out-dir", d, *SMALL, "--arch", "MSC", "--arch", "SKF:s3")
    summary = json.loads((d / "summary.json").read_text())
    assert list(summary["architectures"]) == ["MSC", "SKF:s3"]


# ------------------------------------------------------------------------------------------
# simulate / estimate / evaluate one by one
# ------------------------------------------------------------------------------------------


def test_stages_separately(tmp_path: Path) -> None:
    s, e, r, j = (tmp_path / n for n in ("s.mcap", "e.mcap", "ev.rrd", "sum.json"))
    res = ok("simulate", AJGL, "-o", s, *SMALL, "--seed", "11")
    assert res.stdout.strip() == f"{s}: 200 runs x 11 steps, 44 messages"
    res = ok("estimate", s, "-o", e, "--arch", "CKF", "--arch", "SKF:s2")
    assert res.stdout.strip() == f"{e}: CKF, SKF:s2 on 200 runs"
    assert sorted(McapFile(e).topics) == ["/estimates/CKF", "/estimates/SKF:s2"]
    res = ok("evaluate", s, e, "-o", r, "--summary", j)
    summary = json.loads(j.read_text())
    assert summary["seed"] == 11 and list(summary["architectures"]) == ["CKF", "SKF:s2"]
    assert "SKF:s2" in res.stdout and str(r) in res.stdout
    assert listing(tmp_path) == ["e.mcap", "ev.rrd", "s.mcap", "sum.json"]
    # evaluate without --summary writes only the recording
    ok("evaluate", s, e, "-o", tmp_path / "ev2.rrd")
    assert listing(tmp_path) == ["e.mcap", "ev.rrd", "ev2.rrd", "s.mcap", "sum.json"]
    # the SKF on s2 is a single-sensor filter: worse than the centralised one
    a = summary["architectures"]
    assert a["SKF:s2"]["expected"]["mse"] > a["CKF"]["expected"]["mse"]


def test_estimate_defaults_to_the_scenarios_architectures(ajgl_run: Path, tmp_path: Path) -> None:
    e = tmp_path / "e.mcap"
    ok("estimate", ajgl_run / "sensors.mcap", "-o", e)
    assert sorted(McapFile(e).topics) == sorted(f"/estimates/{a}" for a in ARCHS)
    # and the estimates are those `run` wrote
    assert_same_arrays(all_arrays(e), all_arrays(ajgl_run / "estimates.mcap"))


@pytest.mark.parametrize("arch", ["XKF", "SKF:nosuch", "CKF:s1"])
def test_unknown_architecture_is_one_line(ajgl_run: Path, tmp_path: Path, arch: str) -> None:
    out = tmp_path / "out"
    out.mkdir()
    res = cli("estimate", ajgl_run / "sensors.mcap", "-o", out / "e.mcap", "--arch", arch)
    one_line_error(res, "--arch", repr(arch))
    res = cli("run", AJGL, "--out-dir", out, *SMALL, "--arch", "CKF", "--arch", arch)
    one_line_error(res, "--arch", repr(arch))
    assert listing(out) == []


# ------------------------------------------------------------------------------------------
# determinism
# ------------------------------------------------------------------------------------------


@needs_fusionlog
def test_same_seed_gives_byte_identical_mcap_files(tmp_path: Path) -> None:
    """The same command (same relative paths) in two folders: byte-identical MCAP files.

    Provenance records the command line but no clock, and MCAP writing is deterministic, so
    identical commands give identical bytes. (With different output paths the files differ
    only in the recorded command; the decoded data are identical, see the next test.)
    """
    dirs = [tmp_path / "a", tmp_path / "b"]
    for d in dirs:
        d.mkdir()
        p = run_proc("simulate", AJGL, "-o", "s.mcap", *SMALL, cwd=d)
        assert p.returncode == 0, p.stderr
        p = run_proc("estimate", "s.mcap", "-o", "e.mcap", cwd=d)
        assert p.returncode == 0, p.stderr
    for name in ("s.mcap", "e.mcap"):
        assert (dirs[0] / name).read_bytes() == (dirs[1] / name).read_bytes(), name


def test_same_seed_identical_arrays_different_seed_not(tmp_path: Path) -> None:
    for name, seed in (("a", "5"), ("b", "5"), ("c", "6")):
        ok("simulate", AJGL, "-o", tmp_path / f"{name}_s.mcap", *SMALL, "--seed", seed)
        ok("estimate", tmp_path / f"{name}_s.mcap", "-o", tmp_path / f"{name}_e.mcap")
    for kind in ("s", "e"):
        a = all_arrays(tmp_path / f"a_{kind}.mcap")
        assert_same_arrays(a, all_arrays(tmp_path / f"b_{kind}.mcap"))
        c = all_arrays(tmp_path / f"c_{kind}.mcap")
        assert not np.array_equal(
            a["/truth" if kind == "s" else "/estimates/CKF:mean"],
            c.get("/truth" if kind == "s" else "/estimates/CKF:mean"),
        )
    # provenance names the seed and, for estimates, the sensors file they came from
    prov = McapFile(tmp_path / "a_e.mcap").metadata["fusionlog.provenance"]
    assert prov["seed"] == "5" and prov["sensors_file"] == "a_s.mcap"
    import hashlib

    assert (
        prov["sensors_sha256"] == hashlib.sha256((tmp_path / "a_s.mcap").read_bytes()).hexdigest()
    )


def test_block_runs_does_not_change_the_numbers(tmp_path: Path) -> None:
    """The hidden --block-runs only sets memory use.

    Truth and measurements are bit-identical whatever the block size (each run has its own
    random stream). Estimates agree to a few ulp but not always bitwise: each block is one
    matrix product with the (shared) gains, and BLAS picks its kernel -- hence the order of
    the additions -- by the number of rows (seen: 7-run blocks differ from 200-run ones by
    ~1e-15 relative; 64 and 200 agreed bitwise). Metrics are sums over blocks, grouped
    differently, so they agree to rounding too.
    """
    arrays, summaries = {}, {}
    for b in ("7", "64", None):
        tag = b or "default"
        s, e = tmp_path / f"s{tag}.mcap", tmp_path / f"e{tag}.mcap"
        opt = ["--block-runs", b] if b else []
        ok("simulate", AJGL, "-o", s, *SMALL, *opt)
        ok("estimate", s, "-o", e, *opt)
        j = tmp_path / f"sum{tag}.json"
        ok("evaluate", s, e, "-o", tmp_path / f"ev{tag}.rrd", "--summary", j, *opt)
        arrays[tag] = {**all_arrays(s), **all_arrays(e)}
        summaries[tag] = json.loads(j.read_text())
    assert len(arrays["default"]) == 4 + 2 * len(ARCHS)
    # the files really were written in different blocks of runs
    assert McapFile(tmp_path / "s7.mcap").topics["/truth"] == 11 * math.ceil(200 / 7)
    assert McapFile(tmp_path / "sdefault.mcap").topics["/truth"] == 11
    for tag in ("7", "64"):
        a, b = arrays[tag], arrays["default"]
        assert a.keys() == b.keys()
        for k in a:
            if k.startswith("/estimates/"):
                np.testing.assert_allclose(a[k], b[k], rtol=1e-12, atol=1e-12, err_msg=k)
            else:
                assert np.array_equal(a[k], b[k]), k
        assert compare_summaries(summaries[tag], summaries["default"], rtol=1e-12) == []


# ------------------------------------------------------------------------------------------
# third-party decoding
# ------------------------------------------------------------------------------------------

THIRD_PARTY_READER = textwrap.dedent(
    """
    # Reads a fusionlog MCAP with nothing but mcap + mcap-protobuf-support.
    import json, sys
    from mcap.reader import make_reader
    from mcap_protobuf.decoder import DecoderFactory

    out = {"metadata": {}, "messages": []}
    with open(sys.argv[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        out["metadata"] = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        for schema, channel, message, msg in reader.iter_decoded_messages(log_time_order=False):
            row = {"topic": channel.topic, "schema": schema.name,
                   "log_time": message.log_time, "publish_time": message.publish_time}
            for name in ("step", "time", "run_offset", "runs", "dim"):
                row[name] = getattr(msg, name)
            for name in ("values", "mean", "covariance"):
                if hasattr(msg, name):
                    row[name] = list(getattr(msg, name))
            out["messages"].append(row)
    assert not [m for m in sys.modules if m.startswith("fusionlog")], "fusionlog was imported"
    json.dump(out, sys.stdout)
    """
)


def third_party_arrays(path: Path, tmp_path: Path) -> tuple[dict[str, np.ndarray], dict]:
    """Decode in a separate, isolated interpreter; assemble the same arrays as all_arrays."""
    script = tmp_path / "third_party_reader.py"
    script.write_text(THIRD_PARTY_READER)
    proc = subprocess.run(
        [sys.executable, "-I", str(script), str(path)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={k: v for k, v in ENV.items() if k != "PYTHONPATH"},
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    msgs = doc["messages"]
    runs = max(m["run_offset"] + m["runs"] for m in msgs)
    steps = max(m["step"] for m in msgs) + 1
    out: dict[str, np.ndarray] = {}
    for m in msgs:
        assert m["log_time"] == m["publish_time"] == round(m["time"] * 1e9)
        o, r, k, d, t = m["run_offset"], m["runs"], m["step"], m["dim"], m["topic"]
        if "values" in m:
            assert m["schema"] == "fusionlog.Block"
            arr = out.setdefault(t, np.full((runs, steps, d), np.nan))
            arr[o : o + r, k] = np.reshape(m["values"], (r, d))
        else:
            assert m["schema"] == "fusionlog.EstimateBlock"
            mean = out.setdefault(t + ":mean", np.full((runs, steps, d), np.nan))
            mean[o : o + r, k] = np.reshape(m["mean"], (r, d))
            cov = np.asarray(m["covariance"])
            assert cov.size == d * d  # one shared covariance per message for these files
            shared = out.setdefault(t + ":cov", np.full((steps, d, d), np.nan))
            shared[k] = cov.reshape(d, d)
    return out, doc["metadata"]


def test_third_party_decoder_gives_the_same_arrays(ajgl_run: Path, tmp_path: Path) -> None:
    for name in ("sensors.mcap", "estimates.mcap"):
        path = ajgl_run / name
        theirs, meta = third_party_arrays(path, tmp_path)
        assert_same_arrays(theirs, all_arrays(path))
        assert sorted(meta) == ["fusionlog.layout", "fusionlog.provenance", "fusionlog.scenario"]
    # the scenario TOML travels inside the file
    _, meta = third_party_arrays(ajgl_run / "sensors.mcap", tmp_path)
    assert meta["fusionlog.scenario"]["toml"] == AJGL.read_text()
    assert meta["fusionlog.scenario"]["runs"] == "200"


def test_third_party_decoder_on_blocked_file(tmp_path: Path) -> None:
    s = tmp_path / "s.mcap"
    ok("simulate", HETERO, "-o", s, "--runs", "30", "--steps", "6", "--block-runs", "8")
    theirs, _ = third_party_arrays(s, tmp_path)
    assert_same_arrays(theirs, all_arrays(s))


@needs_rerun
def test_rerun_mcap_check_and_convert(ajgl_run: Path, tmp_path: Path) -> None:
    for name in ("sensors.mcap", "estimates.mcap"):
        path = ajgl_run / name
        p = run_proc(RERUN, "mcap", "check", path)
        assert p.returncode == 0, p.stdout + p.stderr
        rrd = tmp_path / (name + ".rrd")
        p = run_proc(
            RERUN,
            "mcap",
            "convert",
            path,
            "-o",
            rrd,
            "-d",
            "protobuf",
            "-d",
            "metadata",
            "--application-id",
            "t",
            "--recording-id",
            "r",
        )
        assert p.returncode == 0, p.stderr
        assert rrd.stat().st_size > 0
        from rerun.chunk import RrdReader

        entities = {str(c.entity_path) for c in RrdReader(str(rrd)).store().stream().to_chunks()}
        topics = set(McapFile(path).topics)
        assert {t.replace(":", "\\:") for t in topics} <= entities, entities


# ------------------------------------------------------------------------------------------
# a real one-run log written by someone else
# ------------------------------------------------------------------------------------------

HAND_MODEL = """\
# A model-only file: no [scenario] needed.
[model]
F = [[1.0, 1.0], [0.0, 1.0]]
Q = [[0.0533, 0.08], [0.08, 0.16]]

[prior]
mean = [0.0, 1.0]
cov = [[4.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "a"
H = [[1.0, 0.0]]
R = 1.0

[[sensors]]
name = "b"
H = [[1.0, 0.0], [0.0, 1.0]]
R = [[2.0, 0.3], [0.3, 0.5]]
"""

HAND_F = np.array([[1.0, 1.0], [0.0, 1.0]])
HAND_Q = np.array([[0.0533, 0.08], [0.08, 0.16]])
HAND_M0, HAND_P0 = np.array([0.0, 1.0]), np.diag([4.0, 1.0])
HAND_H = {"a": np.array([[1.0, 0.0]]), "b": np.eye(2)}
HAND_R = {"a": np.array([[1.0]]), "b": np.array([[2.0, 0.3], [0.3, 0.5]])}
HAND_STEPS = 50
HAND_MISSING_B = (10, 11, 12)  # steps where sensor b has no reading (NaN)


def write_hand_log(path: Path) -> dict[str, np.ndarray]:
    """A one-run sensor log in the documented layout, written with the plain `mcap` Writer and
    protobuf classes built from a descriptor: no fusionlog code involved, no metadata."""
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
    from mcap.writer import Writer

    FD = descriptor_pb2.FieldDescriptorProto
    fdp = descriptor_pb2.FileDescriptorProto(name="lab/block.proto", package="lab", syntax="proto3")
    msg = fdp.message_type.add(name="Block")
    for name, number, typ in (
        ("step", 1, FD.TYPE_UINT32),
        ("time", 2, FD.TYPE_DOUBLE),
        ("run_offset", 3, FD.TYPE_UINT32),
        ("runs", 4, FD.TYPE_UINT32),
        ("dim", 5, FD.TYPE_UINT32),
        ("values", 6, FD.TYPE_DOUBLE),
    ):
        label = FD.LABEL_REPEATED if name == "values" else FD.LABEL_OPTIONAL
        msg.field.add(name=name, number=number, type=typ, label=label)
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    Block = message_factory.GetMessageClass(pool.FindMessageTypeByName("lab.Block"))
    fds = descriptor_pb2.FileDescriptorSet(file=[fdp]).SerializeToString()

    rng = np.random.default_rng(42)
    x = rng.multivariate_normal(HAND_M0, HAND_P0)
    z = {"a": np.empty((HAND_STEPS, 1)), "b": np.empty((HAND_STEPS, 2))}
    for k in range(HAND_STEPS):
        if k:
            x = HAND_F @ x + rng.multivariate_normal(np.zeros(2), HAND_Q)
        for s in ("a", "b"):
            z[s][k] = HAND_H[s] @ x + rng.multivariate_normal(np.zeros(len(HAND_R[s])), HAND_R[s])
    z["b"][list(HAND_MISSING_B)] = np.nan

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="lab-logger 1.0")
        sid = w.register_schema("lab.Block", "protobuf", fds)
        chans = {s: w.register_channel(f"/sensors/{s}", "protobuf", sid) for s in ("a", "b")}
        for k in range(HAND_STEPS):
            t = 0.1 * k
            ns = round(t * 1e9)
            for s, cid in chans.items():
                m = Block(step=k, time=t, run_offset=0, runs=1, dim=z[s].shape[1])
                m.values.extend(z[s][k])
                w.add_message(cid, log_time=ns, publish_time=ns, data=m.SerializeToString())
        w.finish()
    return z


def reference_ckf(z: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Textbook centralised KF (prior = p(x_0 | z_-1)); a missing sensor is skipped."""
    x, P = HAND_M0.copy(), HAND_P0.copy()
    means, covs = [], []
    for k in range(HAND_STEPS):
        if k:
            x, P = HAND_F @ x, HAND_F @ P @ HAND_F.T + HAND_Q
        for s in ("a", "b"):
            if np.isnan(z[s][k]).any():
                continue
            H, R = HAND_H[s], HAND_R[s]
            S = H @ P @ H.T + R
            K = np.linalg.solve(S, H @ P).T
            x = x + K @ (z[s][k] - H @ x)
            P = (np.eye(2) - K @ H) @ P
            P = 0.5 * (P + P.T)
        means.append(x)
        covs.append(P)
    return np.array(means), np.array(covs)


def test_hand_written_one_run_log_replays_with_model(tmp_path: Path) -> None:
    log = tmp_path / "lab.mcap"
    z = write_hand_log(log)
    model = write_toml(tmp_path / "model.toml", HAND_MODEL)
    out = tmp_path / "out"
    out.mkdir()
    est = out / "e.mcap"
    res = ok("estimate", log, "-o", est, "--model", model, *sum([["--arch", a] for a in ARCHS], []))
    assert "on 1 runs" in res.stdout
    f = McapFile(est)
    assert f.runs() == 1 and f.steps() == HAND_STEPS
    assert f.times()[-1] == pytest.approx(0.1 * (HAND_STEPS - 1))
    assert sorted(f.topics) == sorted(f"/estimates/{a}" for a in ARCHS)
    assert set(f.topics.values()) == {HAND_STEPS}
    data = f.read_all([f"/estimates/{a}" for a in ARCHS])
    for a in ARCHS:
        mean, cov = data[f"/estimates/{a}"]
        assert mean.shape == (1, HAND_STEPS, 2) and np.isfinite(mean).all(), a
        assert np.isfinite(cov).all(), a
    # the centralised filter is the textbook KF on both sensors
    m_ref, P_ref = reference_ckf(z)
    mean, cov = data["/estimates/CKF"]
    np.testing.assert_allclose(mean[0], m_ref, rtol=1e-9, atol=1e-9)
    cov = cov if cov.ndim == 3 else cov[0]
    np.testing.assert_allclose(cov, P_ref, rtol=1e-9, atol=1e-12)
    prov = f.metadata["fusionlog.provenance"]
    assert prov["model_source"] == str(model) and "seed" not in prov
    assert "fusionlog.scenario" not in f.metadata  # there was none to copy
    assert listing(out) == ["e.mcap"]


def test_hand_written_log_without_model_says_pass_model(tmp_path: Path) -> None:
    log = tmp_path / "lab.mcap"
    write_hand_log(log)
    out = tmp_path / "out"
    out.mkdir()
    res = cli("estimate", log, "-o", out / "e.mcap")
    one_line_error(res, str(log), "--model")
    assert listing(out) == []


def test_model_sensor_missing_from_log(tmp_path: Path) -> None:
    log = tmp_path / "lab.mcap"
    write_hand_log(log)
    model = write_toml(tmp_path / "m.toml", HAND_MODEL.replace('name = "b"', 'name = "c"'))
    res = cli("estimate", log, "-o", tmp_path / "e.mcap", "--model", model)
    one_line_error(res, str(log), "/sensors/c")
    assert not (tmp_path / "e.mcap").exists()


# ------------------------------------------------------------------------------------------
# bad input: exit 2, one line, no traceback, nothing left in the output folder
# ------------------------------------------------------------------------------------------

BASE_SCENARIO = """\
[scenario]
name = "bad"
steps = 5
runs = 10
seed = 1
dt = 1.0

[model]
F = [[1.0, 1.0], [0.0, 1.0]]
Q = [[0.05, 0.08], [0.08, 0.16]]

[prior]
mean = [0.0, 1.0]
cov = [[1.0, 0.0], [0.0, 1.0]]

[[sensors]]
name = "a"
H = [[1.0, 0.0]]
R = [[1.0]]
"""


def test_base_scenario_is_valid(tmp_path: Path) -> None:
    sc = write_toml(tmp_path / "ok.toml", BASE_SCENARIO)
    ok("simulate", sc, "-o", tmp_path / "s.mcap")


@pytest.mark.parametrize(
    "old, new, fragments",
    [
        (
            "cov = [[1.0, 0.0], [0.0, 1.0]]",
            "cov = [[1.0, 0.5], [0.0, 1.0]]",
            ["prior.cov", "not symmetric"],
        ),
        ("R = [[1.0]]", "R = [[-1.0]]", ["sensors[0].R", "not positive definite"]),
        (
            "Q = [[0.05, 0.08], [0.08, 0.16]]",
            "Q = [[0.05, 0.5], [0.5, 0.16]]",
            ["model.Q", "not positive semidefinite"],
        ),
        ("H = [[1.0, 0.0]]", "H = [[1.0, 0.0, 0.0]]", ["sensors[0].H", "shape 1x3"]),
        (
            "F = [[1.0, 1.0], [0.0, 1.0]]",
            "F = [[1.0, 1.0, 0.0], [0.0, 1.0, 0.0]]",
            ["model.F", "square"],
        ),
        ("mean = [0.0, 1.0]", "mean = [0.0, 1.0, 2.0]", ["prior.mean", "length 3"]),
        ('name = "bad"', 'name = "bad"\ncolour = "red"', ["scenario", "unknown key 'colour'"]),
        ("[prior]", "[priors]", ["unknown section 'priors'"]),
        ("mean = [0.0, 1.0]", "mean = [nan, 1.0]", ["prior.mean[0]", "not finite"]),
        ("cov = [[1.0, 0.0], [0.0, 1.0]]", "cov = [[inf, 0.0], [0.0, 1.0]]", ["prior.cov"]),
        ("runs = 10", "runs = 0", ["scenario.runs", ">= 1"]),
        ("steps = 5", "steps = 5.5", ["scenario.steps", "integer"]),
        ("dt = 1.0", 'dt = 1.0\n[estimate]\narchitectures = ["XKF"]', ["XKF"]),
        ("[[sensors]]", "[[sensors]", ["invalid TOML"]),
    ],
    ids=[
        "nonsymmetric",
        "R-not-pd",
        "Q-not-psd",
        "H-shape",
        "F-not-square",
        "mean-length",
        "unknown-key",
        "unknown-section",
        "nan-prior",
        "inf-cov",
        "zero-runs",
        "float-steps",
        "unknown-arch-in-scenario",
        "toml-syntax",
    ],
)
def test_invalid_scenario(tmp_path: Path, old: str, new: str, fragments: list[str]) -> None:
    assert old in BASE_SCENARIO
    sc = write_toml(tmp_path / "bad.toml", BASE_SCENARIO.replace(old, new, 1))
    out = tmp_path / "out"
    out.mkdir()
    for cmd in (["simulate", sc, "-o", out / "s.mcap"], ["run", sc, "--out-dir", out]):
        res = cli(*cmd)
        one_line_error(res, str(sc), *fragments)
        assert listing(out) == []


def test_invalid_model_file_for_estimate(ajgl_run: Path, tmp_path: Path) -> None:
    model = write_toml(tmp_path / "m.toml", HAND_MODEL.replace("R = 1.0", "R = -1.0"))
    out = tmp_path / "out"
    out.mkdir()
    res = cli("estimate", ajgl_run / "sensors.mcap", "-o", out / "e.mcap", "--model", model)
    one_line_error(res, str(model), "sensors[0].R", "positive definite")
    assert listing(out) == []


def test_a_replay_file_is_not_a_filter_model(ajgl_run: Path, tmp_path: Path) -> None:
    """A replay file as --model: one line saying what it is (it said `scenario.dt: missing
    required key`, then `truth: unknown key 'source'`)."""
    replay = ROOT / "pipeline" / "replay_robot.toml"
    out = tmp_path / "out"
    out.mkdir()
    res = cli("estimate", ajgl_run / "sensors.mcap", "-o", out / "e.mcap", "--model", replay)
    one_line_error(res, str(replay), "a replay file, not a filter model")
    assert listing(out) == []


def test_recorded_architecture_the_model_cannot_run(tmp_path: Path) -> None:
    """Without --arch, estimate runs the recorded scenario's architectures; one that names a
    sensor a --model lacks is refused naming the sensors file, not an --arch never given."""
    text = AJGL.read_text()
    archs = 'architectures = ["CKF", "HKF", "MSC-GMF", "MSC", "SKF", "CI", "FBS"]'
    s3 = '[[sensors]]\nname = "s3"\nH = [[1.0, 0.0]]\nR = 1.0\n'
    assert archs in text and s3 in text
    sc = write_toml(tmp_path / "sc.toml", text.replace(archs, 'architectures = ["CKF", "SKF:s3"]'))
    model = write_toml(tmp_path / "m.toml", text.replace(s3, ""))
    log = tmp_path / "s.mcap"
    ok("simulate", sc, "-o", log, "--runs", "20", "--steps", "3")
    res = cli("estimate", log, "-o", tmp_path / "e.mcap", "--model", model)
    line = one_line_error(res, str(log), "recorded architectures", "SKF:s3", "no sensor 's3'")
    assert "--arch" not in line and not (tmp_path / "e.mcap").exists()
    res = cli("estimate", log, "-o", tmp_path / "e.mcap", "--model", model, "--arch", "SKF:s3")
    one_line_error(res, "--arch", "no sensor 's3'")
    ok("estimate", log, "-o", tmp_path / "e.mcap", "--model", model, "--arch", "SKF:s2")


def test_a_model_file_without_scenario_takes_the_recorded_dt(
    ajgl_run: Path, tmp_path: Path
) -> None:
    """README: `estimate --model` takes the scenario's sections without [scenario]. The paper's
    own [model] (constant velocity, N0 = n0 dt) was refused there: "scenario.dt: missing
    required key". The recorded dt stands in: the same model gives the same estimates."""
    text = AJGL.read_text()
    model = write_toml(tmp_path / "m.toml", text[text.index("[model]") :])
    s = ajgl_run / "sensors.mcap"
    ok("estimate", s, "-o", tmp_path / "e.mcap", "--model", model, "--arch", "CKF")
    ok("estimate", s, "-o", tmp_path / "ref.mcap", "--arch", "CKF")
    got = McapFile(tmp_path / "e.mcap").read_all(["/estimates/CKF"])["/estimates/CKF"]
    ref = McapFile(tmp_path / "ref.mcap").read_all(["/estimates/CKF"])["/estimates/CKF"]
    for a, b in zip(got, ref, strict=True):
        np.testing.assert_array_equal(a, b)


def test_invalid_override(tmp_path: Path) -> None:
    res = cli("simulate", AJGL, "-o", tmp_path / "s.mcap", "--runs", "0")
    one_line_error(res, "--runs")
    assert listing(tmp_path) == []


@pytest.fixture(scope="module")
def truncated(tmp_path_factory) -> Path:
    """A sensors file cut at 60 %: several chunks and blocks, so the start stays readable."""
    d = tmp_path_factory.mktemp("trunc")
    full = d / "full.mcap"
    ok("simulate", AJGL, "-o", full, "--runs", "4000", "--steps", "10", "--block-runs", "500")
    data = full.read_bytes()
    cut = d / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    return cut


def test_truncated_mcap_is_one_line(truncated: Path, tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    res = cli("estimate", truncated, "-o", out / "e.mcap")
    line = one_line_error(res, str(truncated), "truncated")
    assert f"fusionlog inspect --recover {truncated}" in line
    res = cli("evaluate", truncated, truncated, "-o", out / "ev.rrd")
    one_line_error(res, str(truncated), "truncated")
    res = cli("inspect", truncated)
    one_line_error(res, str(truncated), "truncated", "--recover")
    assert listing(out) == []


def test_inspect_recover_reports_what_is_readable(truncated: Path) -> None:
    res = ok("inspect", "--recover", truncated)
    out = res.stdout
    assert out.splitlines()[0].startswith(f"{truncated}: damaged: ")
    counts = {}
    for line in out.splitlines()[1:]:
        parts = line.split()
        if parts and parts[0].startswith("/"):
            counts[parts[0]] = int(parts[1])
    assert set(counts) == {"/truth", "/sensors/s1", "/sensors/s2", "/sensors/s3"}
    assert all(c > 0 for c in counts.values())
    complete = int(out.split("complete runs: ")[1].split(",")[0])
    assert complete > 0 and complete % 500 == 0 and complete < 4000
    assert "metadata: fusionlog.provenance, fusionlog.scenario" in out


def test_inspect_recover_on_intact_file(ajgl_run: Path) -> None:
    res = ok("inspect", "--recover", ajgl_run / "sensors.mcap")
    assert res.stdout.splitlines()[0].endswith(": intact")
    assert "complete runs: 200, last complete step: 10" in res.stdout


def test_inspect_intact_file(ajgl_run: Path) -> None:
    res = ok("inspect", ajgl_run / "estimates.mcap")
    out = res.stdout
    assert "scenario: ajgl2009 (seed 2009)" in out
    assert "runs: 200, instants: 11 (k = 0..10)" in out
    for a in ARCHS:
        assert f"/estimates/{a}" in out
    assert "fusionlog.EstimateBlock" in out


def write_foreign_mcap(path: Path) -> None:
    """A valid MCAP file with nothing of fusionlog's in it."""
    from mcap.writer import Writer

    with open(path, "wb") as fh:
        w = Writer(fh)
        w.start(profile="", library="other")
        sid = w.register_schema("Foo", "jsonschema", b"{}")
        cid = w.register_channel("/foo", "json", sid)
        for k in range(5):
            w.add_message(cid, log_time=k, publish_time=k, data=b"{}")
        w.finish()


def test_mcap_without_fusionlog_topics(tmp_path: Path) -> None:
    foo = tmp_path / "foo.mcap"
    write_foreign_mcap(foo)
    model = write_toml(tmp_path / "m.toml", HAND_MODEL)
    out = tmp_path / "out"
    out.mkdir()
    res = cli("estimate", foo, "-o", out / "e.mcap")
    one_line_error(res, str(foo), "--model")
    res = cli("estimate", foo, "-o", out / "e.mcap", "--model", model)
    one_line_error(res, str(foo), "no topic /sensors/a", "/foo")
    res = cli("evaluate", foo, foo, "-o", out / "e.rrd")
    one_line_error(res, str(foo), "/truth")
    res = ok("inspect", "--recover", foo)
    assert "/foo" in res.stdout and "intact" in res.stdout
    assert listing(out) == []


def test_inspect_lists_foreign_topics(tmp_path: Path) -> None:
    foo = tmp_path / "foo.mcap"
    write_foreign_mcap(foo)
    res = cli("inspect", foo)
    assert res.exit_code == 0 and "/foo" in res.stdout


@pytest.mark.parametrize("content", [b"", b"not an mcap file at all", b"\x89MCAP0\r\n"])
def test_not_mcap(tmp_path: Path, content: bytes) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(content)
    out = tmp_path / "out"
    out.mkdir()
    res = cli("estimate", bad, "-o", out / "e.mcap")
    one_line_error(res, str(bad))
    assert listing(out) == []


def test_evaluate_mismatched_files(ajgl_run: Path, tmp_path: Path) -> None:
    s = tmp_path / "s.mcap"
    ok("simulate", AJGL, "-o", s, "--runs", "20", "--steps", "10")
    out = tmp_path / "out"
    out.mkdir()
    res = cli("evaluate", s, ajgl_run / "estimates.mcap", "-o", out / "ev.rrd")
    one_line_error(res, "another sensors file")
    # estimates given where the sensors should be
    res = cli("evaluate", ajgl_run / "estimates.mcap", ajgl_run / "estimates.mcap", "-o", out / "x")
    one_line_error(res, "/truth")
    assert listing(out) == []


def test_outputs_exist_without_force(ajgl_run: Path, tmp_path: Path) -> None:
    s, e = ajgl_run / "sensors.mcap", ajgl_run / "estimates.mcap"
    targets = {name: tmp_path / name for name in ("s.mcap", "e.mcap", "ev.rrd", "sum.json")}
    for p in targets.values():
        p.write_bytes(b"precious")
    before = snapshot(targets.values())
    cases = [
        (["simulate", AJGL, "-o", targets["s.mcap"], *SMALL], targets["s.mcap"]),
        (["estimate", s, "-o", targets["e.mcap"]], targets["e.mcap"]),
        (["evaluate", s, e, "-o", targets["ev.rrd"]], targets["ev.rrd"]),
        (
            ["evaluate", s, e, "-o", tmp_path / "new.rrd", "--summary", targets["sum.json"]],
            targets["sum.json"],
        ),
    ]
    for args, existing in cases:
        res = cli(*args)
        one_line_error(res, str(existing), "exists", "--force")
    assert snapshot(targets.values()) == before
    assert listing(tmp_path) == sorted(targets)  # not even new.rrd was written
    # --force replaces them
    ok("simulate", AJGL, "-o", targets["s.mcap"], "--runs", "20", "--steps", "3", "--force")
    assert McapFile(targets["s.mcap"]).runs() == 20


def test_missing_input_files(ajgl_run: Path, tmp_path: Path) -> None:
    nope = tmp_path / "nope"
    s, e = ajgl_run / "sensors.mcap", ajgl_run / "estimates.mcap"
    out = tmp_path / "out"
    out.mkdir()
    cases = [
        ["simulate", nope.with_suffix(".toml"), "-o", out / "s.mcap"],
        ["run", nope.with_suffix(".toml"), "--out-dir", out],
        ["estimate", nope.with_suffix(".mcap"), "-o", out / "e.mcap"],
        ["estimate", s, "-o", out / "e.mcap", "--model", nope.with_suffix(".toml")],
        ["evaluate", nope.with_suffix(".mcap"), e, "-o", out / "ev.rrd"],
        ["evaluate", s, nope.with_suffix(".mcap"), "-o", out / "ev.rrd"],
        ["summary", nope.with_suffix(".rrd")],
        ["summary", nope.with_suffix(".rrd"), "--json"],
        ["compare", nope.with_suffix(".json"), ajgl_run / "summary.json"],
        ["compare", ajgl_run / "summary.json", nope.with_suffix(".json")],
        ["inspect", nope.with_suffix(".mcap")],
        ["inspect", "--recover", nope.with_suffix(".mcap")],
    ]
    for args in cases:
        missing = next(a for a in args if isinstance(a, Path) and a.stem == "nope")
        res = cli(*args)
        one_line_error(res, str(missing))
    assert listing(out) == []


def test_debug_flag_in_process(tmp_path: Path, monkeypatch) -> None:
    """--debug lets the exception through; it is read from the parsed options, not from the
    host's sys.argv (an embedding program or `pytest --debug` must not switch it on)."""
    from fusionlog.errors import ValidationError

    nope = tmp_path / "nope.toml"
    res = cli("--debug", "simulate", nope, "-o", tmp_path / "s.mcap")
    assert isinstance(res.exception, ValidationError) and str(nope) in str(res.exception)
    monkeypatch.setattr(sys, "argv", ["host", "--debug"])
    one_line_error(cli("simulate", nope, "-o", tmp_path / "s.mcap"), str(nope))


def test_input_is_a_directory(tmp_path: Path) -> None:
    res = cli("estimate", tmp_path, "-o", tmp_path / "e.mcap")
    # click's own usage error: exit 2, no traceback
    assert res.exit_code == 2 and "Traceback" not in res.output
    assert "directory" in res.stderr


def test_summary_of_a_non_recording(ajgl_run: Path) -> None:
    res = cli("summary", ajgl_run / "summary.json")
    one_line_error(res, str(ajgl_run / "summary.json"))


def test_a_damaged_recording_or_bag_is_not_sent_to_inspect_recover(
    ajgl_run: Path, tmp_path: Path
) -> None:
    """`inspect --recover` reads MCAP files only: the hint it shows what is readable was also
    given for a truncated .rrd and a damaged ROS 1 bag, where it then failed (not MCAP)."""
    rrd = tmp_path / "cut.rrd"
    rrd.write_bytes((ajgl_run / "evaluation.rrd").read_bytes()[:3000])
    line = one_line_error(cli("summary", rrd), str(rrd), "Rerun recording")
    assert "--recover" not in line
    bag = tmp_path / "cut.bag"
    data = (ROOT / "pipeline" / "data" / "gps_ros1.bag").read_bytes()
    bag.write_bytes(data[: len(data) // 2])
    line = one_line_error(cli("inspect", bag), str(bag), "damaged")
    assert "--recover" not in line


def test_python_dash_m_fusionlog_is_the_command(ajgl_run: Path) -> None:
    """`python -m fusionlog` (no console script on PATH) failed: no fusionlog.__main__."""
    summary = str(ajgl_run / "summary.json")

    def dash_m(*args: str) -> subprocess.CompletedProcess:
        cmd = [sys.executable, "-m", "fusionlog", *args]
        return subprocess.run(cmd, capture_output=True, text=True, env=ENV, timeout=120)

    p = dash_m("compare", summary, summary)
    assert p.returncode == 0 and "matches" in p.stdout, p.stderr
    p = dash_m("inspect")
    assert p.returncode == 2 and p.stderr.startswith("fusionlog: error: Missing argument")


def test_a_reader_that_leaves_early_is_not_an_error(ajgl_run: Path) -> None:
    """`fusionlog inspect X | head -1`: stdout's reader has gone; fusionlog stops quietly with
    128 + SIGPIPE (it printed "fusionlog: error: Broken pipe" and exited 2, as for bad input)."""
    cmd = [sys.executable, "-m", "fusionlog.cli", "inspect", str(ajgl_run / "sensors.mcap")]
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=ENV) as p:
        assert p.stdout is not None and p.stderr is not None
        p.stdout.close()  # no reader left: the first line written fails with EPIPE
        err = p.stderr.read().decode()
        assert p.wait(timeout=120) == 128 + signal.SIGPIPE, err
    assert err == ""


@needs_fusionlog
def test_exit_codes_and_debug_traceback_as_a_user_sees_them(tmp_path: Path) -> None:
    nope = tmp_path / "nope.toml"
    p = run_proc("simulate", nope, "-o", tmp_path / "s.mcap")
    assert p.returncode == 2
    assert p.stderr.splitlines() == [
        f"fusionlog: error: {nope}: cannot read: No such file or directory"
    ]
    assert p.stdout == ""
    p = run_proc("--debug", "simulate", nope, "-o", tmp_path / "s.mcap")
    assert p.returncode != 0
    assert "Traceback (most recent call last)" in p.stderr
    assert "ValidationError" in p.stderr and str(nope) in p.stderr
    p = run_proc("simulate", AJGL)  # missing -o: a usage error is one line too (issue 19)
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.splitlines() == [
        "fusionlog: error: Missing option '-o' / '--output'. (see: fusionlog simulate --help)"
    ]
    assert listing(tmp_path) == []


# ------------------------------------------------------------------------------------------
# SIGINT and progress bars (real processes)
# ------------------------------------------------------------------------------------------


@needs_fusionlog
def test_sigint_leaves_nothing_behind(tmp_path: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    proc = subprocess.Popen(
        [FUSIONLOG, "simulate", str(AJGL), "-o", str(out / "s.mcap"), "--runs", "600000"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=ENV,
    )
    try:
        # Interrupt while writing: wait until the temporary file exists.
        deadline = time.monotonic() + 30
        while not any(n.endswith(".tmp") for n in listing(out)):
            assert proc.poll() is None, "finished before it could be interrupted"
            assert time.monotonic() < deadline
            time.sleep(0.01)
        time.sleep(0.2)
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert err.splitlines() == ["fusionlog: interrupted; no partial output was left behind"]
    assert listing(out) == []


@needs_fusionlog
def test_quiet_when_piped(tmp_path: Path) -> None:
    p = run_proc("run", AJGL, "--out-dir", tmp_path / "o", "--runs", "3000", "--block-runs", "500")
    assert p.returncode == 0, p.stderr
    assert p.stderr == ""
    assert "CKF" in p.stdout


@needs_fusionlog
@pytest.mark.skipif(sys.platform == "win32", reason="needs a pseudo-terminal")
def test_progress_bar_on_a_terminal(tmp_path: Path) -> None:
    import fcntl
    import pty
    import select
    import struct
    import termios

    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 100, 0, 0))
    args = ["simulate", str(AJGL), "-o", str(tmp_path / "s.mcap"), "--runs", "3000"]
    proc = subprocess.Popen(
        [FUSIONLOG, *args, "--block-runs", "500"],
        stdout=subprocess.DEVNULL,  # not a pipe left open (warnings are errors in the suite)
        stderr=slave,
        env=ENV,
    )
    os.close(slave)
    seen = b""
    try:
        while True:
            ready, _, _ = select.select([master], [], [], 60)
            if not ready:
                break
            try:
                chunk = os.read(master, 4096)
            except OSError:  # EIO: the other side closed
                break
            if not chunk:
                break
            seen += chunk
    finally:
        os.close(master)
        proc.wait(timeout=60)
    assert proc.returncode == 0
    assert b"simulate:" in seen and b"/6 [" in seen, seen  # tqdm bar over 6 blocks


# ------------------------------------------------------------------------------------------
# summary and compare
# ------------------------------------------------------------------------------------------


def test_summary_table_and_json(ajgl_run: Path, tmp_path: Path) -> None:
    rrd = ajgl_run / "evaluation.rrd"
    res = ok("summary", rrd)
    lines = res.stdout.splitlines()
    assert lines[0] == "ajgl2009: M = 200 runs, K = 10"
    assert [ln.split()[0] for ln in lines[3:]] == ARCHS
    res = ok("summary", rrd, "--json")
    from_rrd = json.loads(res.stdout)
    from_file = json.loads((ajgl_run / "summary.json").read_text())
    assert from_rrd == from_file
    assert list(from_rrd["architectures"]) == ARCHS  # order kept
    # the table read back offline is the one `evaluate` printed
    table = "\n".join(lines[1:])
    sens, est = ajgl_run / "sensors.mcap", ajgl_run / "estimates.mcap"
    printed = ok("evaluate", sens, est, "-o", tmp_path / "again.rrd").stdout
    assert table in printed


def test_compare_itself(ajgl_run: Path) -> None:
    j = ajgl_run / "summary.json"
    res = ok("compare", j, j)
    assert "matches" in res.stdout


@pytest.mark.parametrize("arch, metric", [("MSC", "anees"), ("CKF", "mse")])
def test_compare_regression(ajgl_run: Path, tmp_path: Path, arch: str, metric: str) -> None:
    golden = ajgl_run / "summary.json"
    doc = json.loads(golden.read_text())
    doc["architectures"][arch][metric] *= 1 + 1e-4
    actual = tmp_path / "actual.json"
    actual.write_text(json.dumps(doc))
    res = cli("compare", actual, golden, "--rtol", "1e-6")
    assert res.exit_code == 1, res.output
    diff = [ln.strip() for ln in res.stdout.splitlines()[1:]]
    assert len(diff) == 1
    assert diff[0].startswith(f"{arch}: {metric}: actual "), diff
    assert "golden" in diff[0] and "rel. diff 0.0001" in diff[0]
    # within a looser tolerance it passes
    ok("compare", actual, golden, "--rtol", "1e-3")


def test_compare_invalid_json(ajgl_run: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"scenario": ')
    res = cli("compare", bad, ajgl_run / "summary.json")
    one_line_error(res, str(bad), "not valid JSON")
    res = cli("compare", ajgl_run / "summary.json", bad)
    one_line_error(res, str(bad), "not valid JSON")


def test_compare_json_that_is_not_a_summary(ajgl_run: Path, tmp_path: Path) -> None:
    bad = tmp_path / "list.json"
    bad.write_text("[]")
    one_line_error(cli("compare", bad, ajgl_run / "summary.json"), str(bad))


def test_evaluate_refuses_estimates_of_another_sensors_file(ajgl_run: Path, tmp_path: Path) -> None:
    """The estimates file records the sha256 of its sensors file; a mismatch is bad input."""
    other = tmp_path / "other.mcap"
    ok("simulate", AJGL, "-o", other, *SMALL, "--seed", "1")
    res = cli("evaluate", other, ajgl_run / "estimates.mcap", "-o", tmp_path / "x.rrd")
    one_line_error(res, str(ajgl_run / "estimates.mcap"), "another sensors file")
    assert not (tmp_path / "x.rrd").exists()


def test_summary_json_has_the_usual_permissions(ajgl_run: Path) -> None:
    mode = (ajgl_run / "summary.json").stat().st_mode & 0o777
    umask = os.umask(0)
    os.umask(umask)
    assert mode == 0o666 & ~umask


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="threads listed in /proc only")
def test_commands_start_no_blas_threads() -> None:
    """Every command asks OpenBLAS for no threads of its own before numpy is imported
    (`fusionlog.memory.one_blas_thread`): the process then runs on its one thread; a number
    the user chose stays."""
    code = textwrap.dedent(
        """
        import os
        from fusionlog.cli import main
        try:
            main(["inspect", "/nonexistent/sensors.mcap"], standalone_mode=False)
        except BaseException:
            pass
        import numpy
        print(os.environ.get("OPENBLAS_NUM_THREADS"), len(os.listdir("/proc/self/task")))
        """
    )
    env = {k: v for k, v in ENV.items() if k != "OPENBLAS_NUM_THREADS"}
    for given, want in ((None, "1"), ("2", "2")):
        run_env = env if given is None else {**env, "OPENBLAS_NUM_THREADS": given}
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             env=run_env)  # fmt: skip
        setting, threads = out.stdout.split()
        assert setting == want, out.stderr
        if given is None:
            assert threads == "1"


def test_commands_leave_their_objects_to_the_exit() -> None:
    """`fusionlog.memory.leave_objects_at_exit`: nothing is frozen while the process runs (an
    in-process caller keeps its collector), everything is when it exits (the interpreter's
    last collections skip them)."""
    code = textwrap.dedent(
        """
        import atexit, gc
        atexit.register(lambda: print("at exit", gc.get_freeze_count() > 0))  # runs last
        from fusionlog.cli import main
        for _ in range(2):
            try:
                main(["inspect", "/nonexistent/sensors.mcap"], standalone_mode=False)
            except BaseException:
                pass
        print("running", gc.get_freeze_count())
        """
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=ENV)
    assert out.stdout.splitlines() == ["running 0", "at exit True"], out.stderr


def test_a_command_run_in_process_gives_the_caller_its_signal_handlers_back(tmp_path) -> None:
    """The CLI turns SIGTERM/SIGHUP into a clean unwind while its command runs, and only then:
    a program (or a test runner) that calls it in process keeps its own handlers afterwards,
    after a success and after a failure alike."""

    def mine(signum, frame):  # pragma: no cover - never delivered
        raise AssertionError(signum)

    saved = {s: signal.signal(s, mine) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        ok("--version")
        one_line_error(cli("inspect", tmp_path / "absent.mcap"), "absent.mcap")
        assert all(signal.getsignal(s) is mine for s in saved)
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)
