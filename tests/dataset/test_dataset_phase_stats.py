"""The per-phase counts and the estimates of what a run has left (dataset/phase_stats.py)."""

from types import SimpleNamespace

import pytest

from tissuecast.dataset.codes import SampleStatus
from tissuecast.dataset.phase_stats import (PREDICTED_SHARE, PhaseStats, eta_text, failure_kind, whole_set_eta,
                                            work_seconds)


def test_work_seconds_counts_whole_waves():
    # 5 tasks of 2 s on 2 workers: 3 waves (the last one half full still takes 2 s)
    assert work_seconds(5, 2.0, 2) == 6.0
    assert work_seconds(4, 2.0, 2) == 4.0
    assert work_seconds(0, 2.0, 2) == 0.0
    assert work_seconds(3, 1.5, 0) == 4.5  # no workers read as one


def test_whole_set_eta_is_the_measured_range():
    low_share, high_share = PREDICTED_SHARE
    assert 0 < low_share < 1 < high_share
    # 4 basis samples at 1..high x the median, 10 more at low..high x, 2 workers, median 3 s
    low, high = whole_set_eta(3.0, 4, 10, 2)
    assert low == pytest.approx(2 * 3.0 + 5 * low_share * 3.0)
    assert high == pytest.approx(2 * high_share * 3.0 + 5 * high_share * 3.0)
    # the range holds the shares measured in four runs on three meshes (docs/scaling.md): 0.68 .. 3.9
    for measured in (0.68, 2.4, 3.3, 3.9):
        seconds = work_seconds(10, measured * 3.0, 2)
        assert whole_set_eta(3.0, 0, 10, 2)[0] <= seconds <= whole_set_eta(3.0, 0, 10, 2)[1]


def test_eta_text_units():
    assert eta_text(45) == "45 s"
    assert eta_text(12 * 60) == "12 min"
    assert eta_text(3 * 3600) == "3.0 h"
    assert eta_text(float("nan")) == "unknown" and eta_text(float("inf")) == "unknown"


def test_failures_group_by_kind_and_phase_sums():
    reason_a = "attempt 1: SolveTimeout: stopped after 65.2 s, past its time limit of 65 s"
    reason_b = ("attempt 1 from the prediction: SolveTimeout: stopped after 70.1 s, past its time limit of 65 s; "
                "attempt 2: SolveTimeout: stopped after 66.0 s, past its time limit of 65 s")
    assert failure_kind(reason_a) == failure_kind(reason_b) == \
        "SolveTimeout: stopped after # s, past its time limit of # s"
    stats = PhaseStats("simulate")
    for seconds, status, reason, attempts in ((1.0, SampleStatus.DONE, "", 1), (3.0, SampleStatus.FAILED, reason_a, 2),
                                              (2.0, SampleStatus.FAILED, reason_b, 2)):
        stats.add(SimpleNamespace(seconds=seconds, cpu_seconds=seconds / 2, iterations=4, factorizations=1,
                                  attempts=attempts, status=status, reason=reason))
    d = stats.close(2.0).as_dict()
    assert (d["tasks"], d["failed"], d["retried"]) == (3, 2, 2)
    assert d["worker_seconds"] == 6.0 and d["cpu_seconds"] == 3.0 and d["max_seconds"] == 3.0
    assert d["iterations_mean"] == 4.0 and d["factorizations_mean"] == 1.0 and d["median_seconds"] == 2.0
    assert d["failures"] == {"SolveTimeout: stopped after # s, past its time limit of # s": 2}
