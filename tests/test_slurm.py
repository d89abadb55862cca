"""The workflow through a REAL Slurm (issue 8): `--profile profiles/slurm` on a single-node cluster.

`../shared/tools/start-slurm.sh` installs (apt), configures and starts munged, MariaDB + slurmdbd,
slurmctld and slurmd on this machine (root, Debian; idempotent, ~15 s cold, <1 s when running).
The small demo configuration (tests/data/slurm_small.yaml) is then run twice into temporary
directories, at the same time: locally (`--workflow-profile workflow/profiles/default`) and through
Slurm. The test
checks that every job really went through Slurm (sacct: COMPLETED, one job per rule job or group
job, the rule names in the job comment the plugin sets) and that both runs wrote the same files.

Skips cleanly when the script is absent, when not root, or when the cluster does not start.
Run it alone with `python -m pytest -q -n 0 -m slurm -s` (-s prints the timings).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from digests import gpkg_digest, las_digest

pytestmark = [pytest.mark.slurm, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
START_SLURM = Path(__file__).resolve().parents[2] / "shared" / "tools" / "start-slurm.sh"
SNAKEFILE = REPO / "Snakefile"
SMALL_CONFIG = REPO / "tests" / "data" / "slurm_small.yaml"
SLURM_PROFILE = REPO / "profiles" / "slurm"
LOCAL_PROFILE = REPO / "workflow" / "profiles" / "default"

# What both runs build: "all" once the Snakefile includes the last stage (register.smk), until
# then the demo stage only. Set it to ["results/demo/scene.json"] to test the demo stage alone.
TARGETS = (
    ["all"]
    if "workflow/rules/register.smk" in SNAKEFILE.read_text()
    else ["results/demo/scene.json"]
)
# rules the workflow runs in the submitting snakemake (`localrules`, workflow/rules/map.smk)
LOCAL_RULES = {"map_grid", "map_mosaic"}
# per-tile rules the Slurm profile bundles into group jobs (group "tiles")
TILE_RULES = {"map_tile_ortho", "map_tile_elevation", "tile_features"}
# start-slurm.sh creates partition "debug" and account "ci" (SLURM_ACCOUNT) for root.
PARTITION = "debug"
ACCOUNT = "ci"
START_TIMEOUT_S = 600  # a cold start apt-installs slurm + mariadb
RUN_TIMEOUT_S = 900  # each snakemake run, enforced with `timeout -k 10` (about 3 min when idle)
SACCT_WAIT_S = 60  # slurmctld sends job records to slurmdbd asynchronously
# Outputs that legitimately differ between two runs: glob patterns under results/ (none known).
# Every other file must be bit-identical, except JSON files, compared without their timing keys.
# the report page and its summary table print wall-clock stage timings and the build time;
# every number they show from the registration is compared through the JSON files instead
# the register cache (results/cache/register/rift_<key>.npz) is keyed by the orthophoto's path and
# time, and npz members carry their writing time: a cache, not an output
NONDETERMINISTIC: list[str] = ["report/index.html", "report/summary.csv", "cache/register/*.npz"]
# seconds, build_seconds, rank_s, timings_s, seconds_write (cube.json: 0.01 vs 0.02 s under load)
TIMING_KEY = re.compile(r"(^|_)(seconds|s)$|^seconds_")


def _sh(cmd: list[str], timeout: float, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, env=env)


def _tail(text: str, n: int = 40) -> str:
    return "\n".join(text.splitlines()[-n:])


@pytest.fixture(scope="module", autouse=True)
def _real_slurm_conf():
    """conftest.py points SLURM_CONF at an empty file for every other test (local runs do not wait
    for a controller); this module talks to the real cluster, so it gets the system's file back."""
    with pytest.MonkeyPatch.context() as mp:
        if os.environ.get("SLURM_CONF") == "/dev/null":  # conftest.NO_SLURM_CONF
            mp.delenv("SLURM_CONF")
        yield


@pytest.fixture(scope="module")
def slurm_cluster():
    """A running single-node Slurm with accounting; stopped afterwards if this test started it."""
    if not START_SLURM.is_file():
        pytest.skip(f"{START_SLURM} is absent")
    if os.geteuid() != 0:
        pytest.skip("start-slurm.sh needs root")
    env = {**os.environ, "SLURM_ACCOUNTING": "dbd", "SLURM_ACCOUNT": ACCOUNT}
    before = _sh(["bash", str(START_SLURM), "status"], timeout=60, env=env)
    was_running = "running: /run/slurm/slurmctld.pid" in before.stdout
    t0 = time.monotonic()
    try:
        res = _sh(["bash", str(START_SLURM)], timeout=START_TIMEOUT_S, env=env)
    except subprocess.TimeoutExpired:
        pytest.skip(f"start-slurm.sh did not finish in {START_TIMEOUT_S} s")
    seconds = time.monotonic() - t0
    if res.returncode != 0:
        pytest.skip(f"start-slurm.sh failed (rc {res.returncode}):\n{_tail(res.stderr)}")
    print(
        f"\n[slurm] cluster start: {seconds:.1f} s ({'already running' if was_running else 'started'})"
    )
    yield {"start_s": seconds}
    if not was_running:
        _sh(["bash", str(START_SLURM), "stop"], timeout=120, env=env)


def _snakemake(workdir: Path, extra: list[str], env: dict | None = None) -> tuple[str, float]:
    cmd = [
        "timeout", "-k", "10", str(RUN_TIMEOUT_S),
        sys.executable, "-m", "snakemake",
        "-s", str(SNAKEFILE),
        "--directory", str(workdir),
        "--configfile", str(SMALL_CONFIG),
        *extra,
        *TARGETS,
    ]  # fmt: skip
    t0 = time.monotonic()
    res = _sh(cmd, timeout=RUN_TIMEOUT_S + 30, env=env)
    seconds = time.monotonic() - t0
    out = res.stdout + res.stderr
    assert res.returncode == 0, (
        f"snakemake failed (rc {res.returncode}):\n{' '.join(cmd)}\n{_tail(out, 80)}"
    )
    return out, seconds


def _drop_timings(obj):
    if isinstance(obj, dict):
        return {k: _drop_timings(v) for k, v in obj.items() if not TIMING_KEY.search(k)}
    if isinstance(obj, list):
        return [_drop_timings(v) for v in obj]
    return obj


def _node_cpus(most: int = 2) -> int:
    """CPUs of the single Slurm node, at most `most` (the profile's `cores` is 8)."""
    res = _sh(["sinfo", "-h", "-o", "%c"], timeout=30)
    cpus = [int(c) for c in res.stdout.split() if c.isdigit()]
    return max(1, min([most, *cpus]))


def _hashes(workdir: Path) -> dict[str, str]:
    """sha256 of every file under results/ (JSON: of its canonical form without timing keys)."""
    root = workdir / "results"
    out = {}
    for p in sorted(root.rglob("*")):
        rel = p.relative_to(root)
        if not p.is_file() or any(rel.match(g) for g in NONDETERMINISTIC):
            continue
        if p.suffix == ".gpkg":  # by its rows: its last_change is the time of writing
            out[str(rel)] = gpkg_digest(p)
            continue
        if p.suffix in (".las", ".laz"):  # without the header's creation date (day of writing)
            out[str(rel)] = las_digest(p)
            continue
        data = p.read_bytes()
        if p.suffix == ".json":
            canon = _drop_timings(json.loads(data))
            data = json.dumps(canon, sort_keys=True, separators=(",", ":")).encode()
        out[str(rel)] = hashlib.sha256(data).hexdigest()
    return out


def _rules_run(log: str) -> set[str]:
    """Rules whose jobs finished ("Finished jobid: N (Rule: X)"), without the action-less `all`."""
    return set(re.findall(r"Finished jobid: \d+ \(Rule: (\w+)\)", log)) - {"all"}


def _sacct(jobids: list[str]) -> dict[str, dict[str, str]]:
    fields = ["JobID", "State", "ExitCode", "Partition", "Account", "Comment", "SubmitLine"]
    res = _sh(
        ["sacct", "-X", "-P", "-n", "-j", ",".join(jobids), f"--format={','.join(fields)}"],
        timeout=60,
    )
    assert res.returncode == 0, res.stderr
    rows = {}
    for line in res.stdout.splitlines():
        parts = line.split("|", len(fields) - 1)
        if len(parts) == len(fields):
            rows[parts[0]] = dict(zip(fields, parts, strict=True))
    return rows


def _comment(row: dict[str, str]) -> str:
    """The plugin's --comment (rule_<rule>[_wildcards_...] or rule_<group>_<rules>).

    sacct stores Comment only with AccountingStoreFlags=job_comment; SubmitLine (Slurm >= 22.05)
    always has it; scontrol has it while slurmctld keeps the job (MinJobAge=300 s).
    """
    if row["Comment"]:
        return row["Comment"]
    m = re.search(r"--comment\s+'?([^'\s]+)", row["SubmitLine"])
    if m:
        return m.group(1)
    res = _sh(["scontrol", "show", "job", row["JobID"]], timeout=30)
    m = re.search(r"Comment=(\S+)", res.stdout)
    return m.group(1) if m else ""


def test_workflow_through_slurm_equals_local_run(slurm_cluster, tmp_path):
    if shutil.which("timeout") is None:
        pytest.skip("coreutils timeout is missing")

    # 1. local reference run (2 cores, the local profile) and 2. the same through Slurm
    # (partition/account through the profile's environment variables), at the same time: the
    # Slurm run mostly waits for its polls while the local one computes
    local_dir, slurm_dir = tmp_path / "local", tmp_path / "slurm"
    env = {**os.environ, "GEOREG_SLURM_PARTITION": PARTITION, "GEOREG_SLURM_ACCOUNT": ACCOUNT}
    slurm_args = [
        "--profile", str(SLURM_PROFILE),
        "--workflow-profile", "none",
        "--cores", str(_node_cpus()),  # a job wider than the node would never start
        # the plugin polls every N s while jobs finish and adds 10 s per poll that finds none; a
        # job here takes 10-13 s from its submission (most of it snakemake's start-up in the job):
        # N = 13 finds most at the first poll (N = 1 polls at 1, 12, 33 s: 300 s for the run)
        "--slurm-init-seconds-before-status-checks", "13",
        "--slurm-keep-successful-logs",
    ]  # fmt: skip
    with ThreadPoolExecutor(2) as pool:
        local = pool.submit(_snakemake, local_dir,
                            ["--workflow-profile", str(LOCAL_PROFILE), "--cores", "2"])  # fmt: skip
        slurm = pool.submit(_snakemake, slurm_dir, slurm_args, env)
        (local_log, local_s), (slurm_log, slurm_s) = local.result(), slurm.result()
    expected_rules = _rules_run(local_log)
    assert expected_rules, f"the local run executed nothing:\n{_tail(local_log)}"
    print(
        f"[slurm] workflow {TARGETS}: local {local_s:.1f} s, through Slurm {slurm_s:.1f} s "
        f"(cluster start {slurm_cluster['start_s']:.1f} s)"
    )

    # 3. every job went through Slurm and completed there
    jobids = re.findall(r"submitted with SLURM jobid (\d+)", slurm_log)
    assert jobids, f"no job was submitted to Slurm:\n{_tail(slurm_log)}"
    assert len(jobids) == len(set(jobids))
    deadline = time.monotonic() + SACCT_WAIT_S
    while True:
        rows = _sacct(jobids)
        states = {j: rows.get(j, {}).get("State", "MISSING") for j in jobids}
        if all(s == "COMPLETED" for s in states.values()) or time.monotonic() > deadline:
            break
        time.sleep(2)
    assert all(s == "COMPLETED" for s in states.values()), f"sacct states: {states}"
    for j in jobids:
        assert rows[j]["Partition"] == PARTITION and rows[j]["Account"] == ACCOUNT, rows[j]
        assert rows[j]["ExitCode"] == "0:0", rows[j]
    comments = [_comment(rows[j]) for j in jobids]
    assert all(c.startswith("rule_") for c in comments), comments
    # rule names contain underscores: find each expected rule inside the comments
    slurm_rules = {
        r for r in expected_rules if any(re.search(rf"(^|_){r}(_|$)", c) for c in comments)
    }
    assert slurm_rules == expected_rules - LOCAL_RULES, (
        f"rules run locally but not seen in Slurm job comments: "
        f"{expected_rules - LOCAL_RULES - slurm_rules}; local rules submitted: "
        f"{slurm_rules & LOCAL_RULES}\ncomments: {comments}"
    )
    assert LOCAL_RULES <= _rules_run(slurm_log), "the local rules did not run in the Slurm run"
    if expected_rules & TILE_RULES:  # the per-tile jobs ran as group jobs, not one job each
        assert any(c.startswith("rule_tiles_") for c in comments), comments
        n_local_jobs = len(re.findall(r"Finished jobid: \d+ \(Rule: (?!all\))", local_log))
        assert len(jobids) < n_local_jobs, (len(jobids), n_local_jobs)
    # per-job Slurm logs (kept with --slurm-keep-successful-logs)
    logs = list((slurm_dir / ".snakemake" / "slurm_logs").rglob("*.log"))
    assert len(logs) >= len(jobids), logs

    # 4. same outputs, bit for bit
    local_h, slurm_h = _hashes(local_dir), _hashes(slurm_dir)
    assert local_h, "the local run wrote no results"
    assert sorted(local_h) == sorted(slurm_h), (
        f"only local: {sorted(set(local_h) - set(slurm_h))}, "
        f"only Slurm: {sorted(set(slurm_h) - set(local_h))}"
    )
    differ = [f for f in local_h if local_h[f] != slurm_h[f]]
    assert not differ, f"outputs differ between the local and the Slurm run: {differ}"
