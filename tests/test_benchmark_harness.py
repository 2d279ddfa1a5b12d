"""``benchmarks/harness.py``: the paired-difference intervals every benchmark stores, and the record of a run."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from harness import mean_ci, provenance  # noqa: E402


def test_over_trials_the_interval_is_normal():
    # differences 0, 0, +1, 0: mean 0.25, sample s.d. 0.5, half-width 1.96 * 0.5 / 2 = 0.49
    d = mean_ci([0, 0, 1, 0], student=False)
    assert d["mean"] == 0.25 and d["ci95"] == pytest.approx([-0.24, 0.74])


def test_over_seeds_the_interval_is_students_and_reproduces_the_committed_mw_proxy_gain():
    # differences 1, 2, 3: mean 2, s.d. 1, half-width 4.303 / sqrt(3) = 2.4843
    d = mean_ci([1, 2, 3], student=True)
    assert d["mean"] == 2.0 and d["ci95"] == pytest.approx([-0.4843, 4.4843], abs=1e-4)
    results = json.loads((ROOT / "benchmarks" / "results" / "mw_proxy.json").read_text())
    cso, il = results["methods"]["cso"]["per_seed"], results["methods"]["il"]["per_seed"]
    stored = results["cso_minus_il"]
    d = mean_ci([cso[s] - il[s] for s in stored["seeds"]], student=True)
    assert d["mean"] == pytest.approx(stored["mean"]) and d["ci95"] == pytest.approx(stored["ci95"])


def test_one_difference_has_no_interval_and_too_many_seeds_are_refused():
    assert mean_ci([0.5], student=True) == {"mean": 0.5, "ci95": None}
    with pytest.raises(ValueError, match="no t quantile for 11 degrees of freedom"):
        mean_ci([0.0] * 12, student=True)


def test_provenance_names_the_checked_out_commit():
    head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True)
    record = provenance()
    assert record["commit"] == (head.stdout.strip() if head.returncode == 0 else None)
    assert record["date"][:2] == "20" and "CPUs" in record["machine"]
