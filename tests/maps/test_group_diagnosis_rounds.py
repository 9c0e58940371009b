"""The group diagnosis's rounds on an engine (afmid.maps.group_diagnosis.diagnose_representatives): the same
verdicts and the same number of diagnoses as diagnosing the representatives one after another, with a group's
first two representatives in one round. On constructed single-trace diagnoses (an engine that answers each pixel
with a prepared summary): no fit."""

from __future__ import annotations

import itertools
from pathlib import Path
from types import SimpleNamespace

import pytest

from afmid.batch.engine import Outcome
from afmid.maps.group_diagnosis import (NOTHING, UNDECIDED, UNEXPLAINED, GroupVerdict, diagnose_representatives,
                                        fewest_to_settle, leading_candidate, majority, pixel_verdict,
                                        verdict_settled)

FAILS = ("fails", "")  # a pixel whose diagnosis raises (the task's one-line error)
#: (verdict, leading candidate) pairs of the kinds a single-trace diagnosis gives, and a failure.
OUTCOMES = [("missing: viscoelastic", "viscoelastic"), ("missing: viscoelastic + capillary", "viscoelastic"),
            (NOTHING, ""), (UNEXPLAINED, ""), (UNEXPLAINED, "viscoelastic"),
            ("cannot decide: viscoelastic or contact_damping", "viscoelastic"),
            ("cannot decide: contact_damping or viscoelastic", "contact_damping"), ("instrument: filter", ""), FAILS]


def candidate(effect: str) -> dict:
    return {"effect": effect, "delta_bic": -4400.0, "error_after": 0.06}


def summary_of(outcome: tuple[str, str]) -> dict:
    """A diagnosis summary (afmid.diagnosis.diagnose.suggest's keys) that reads as ``outcome``."""
    text, lead = outcome
    if text == NOTHING:
        return {"missing_effect": False}
    diagnosis = {"explained_by_catalog": text.startswith("missing: "), "noise_floor": 0.05, "error_after": 0.06,
                 "delta_bic_after": -4400.0}
    if text.startswith("missing: "):
        return {"missing_effect": True, "diagnosis": diagnosis,
                "suggestions": [candidate(e) for e in text[len("missing: "):].split(" + ")]}
    if text.startswith("cannot decide: "):
        return {"missing_effect": True, "diagnosis": diagnosis, "suggestions": [],
                "undecided": [candidate(e) for e in text[len("cannot decide: "):].split(" or ")]}
    if text.startswith("instrument: "):
        return {"missing_effect": True, "suggestions": [],
                "diagnosis": {**diagnosis, "instrument": {"kind": text[len("instrument: "):]}}}
    return {"missing_effect": True, "diagnosis": diagnosis, "suggestions": [candidate(lead)] if lead else []}


class PreparedEngine:
    """The engine protocol answering each task's pixel with its prepared outcome; records each run's pixels."""

    def __init__(self, outcomes: dict[int, tuple[str, str]]):
        self.outcomes, self.rounds = outcomes, []

    def workers_for(self, n_tasks: int) -> int:
        return 2

    def run(self, worker, tasks, report, tick) -> None:
        self.rounds.append([task["pixel"] for _, task in tasks])
        for key, task in reversed(tasks):  # in any order, as a real engine reports them
            outcome = self.outcomes[task["pixel"]]
            result = {"pixel": task["pixel"], "cpu_s": 1.0}
            result.update({"error": "ValueError: no drive"} if outcome == FAILS else {"summary": summary_of(outcome)})
            report(Outcome(key, result))


def one_after_another(outcomes: list[tuple[str, str]]) -> tuple[str, list[str], int]:
    """The group's (verdict, verdicts of the diagnosed representatives, diagnoses run) when the representatives
    are diagnosed in order and those left are skipped once the verdict is settled."""
    texts, leads, ran = [], [], 0
    for outcome in outcomes:
        if verdict_settled(texts, leads, len(outcomes)):
            break
        ran += 1
        if outcome != FAILS:
            texts.append(outcome[0])
            leads.append(outcome[1])
    return (majority(texts, leads)[0] if texts else UNDECIDED), texts, ran


def new_verdict(group: int) -> GroupVerdict:
    return GroupVerdict(group, 10, 0.5, 6.0, [], NOTHING, False)


SOURCE = SimpleNamespace(path=Path("map.h5"), cols=4)


def test_the_prepared_summaries_read_as_their_outcomes():
    for outcome in OUTCOMES:
        if outcome == FAILS:
            continue
        summary = summary_of(outcome)
        lead = leading_candidate(summary)
        assert (pixel_verdict(summary)[0], lead["effect"] if lead else "") == outcome


def test_rounds_give_the_verdicts_and_the_diagnoses_of_one_after_another():
    """Every outcome of three representatives (failures included): the same group verdict, the same diagnosed
    pixels in the same order and the same number of diagnoses as one after another; the first round holds two
    pixels, and the third runs only when the two do not settle the verdict."""
    for outcomes in itertools.product(OUTCOMES, repeat=3):
        engine = PreparedEngine(dict(zip((7, 3, 12), outcomes)))
        verdict = new_verdict(0)
        diagnose_representatives([(verdict, [7, 3, 12])], SOURCE, "", None, engine)
        want, texts, ran = one_after_another(list(outcomes))
        assert (verdict.verdict, verdict.pixel_verdicts) == (want, texts), outcomes
        assert sum(len(r) for r in engine.rounds) == ran, (outcomes, engine.rounds)
        assert engine.rounds[0] == [7, 3], outcomes
        assert verdict.representatives == [p for p, o in zip((7, 3, 12), outcomes) if o != FAILS][:len(texts)]
        assert verdict.diagnosed


def test_the_groups_share_their_rounds():
    """Two model-limited groups: both groups' first two representatives in the first round (four tasks at once),
    the third of the undecided group alone in the second."""
    agree = {1: OUTCOMES[0], 2: OUTCOMES[0], 3: OUTCOMES[2]}
    differ = {11: OUTCOMES[0], 12: OUTCOMES[3], 13: OUTCOMES[0]}
    engine = PreparedEngine({**agree, **differ})
    first, second = new_verdict(0), new_verdict(1)
    diagnose_representatives([(first, [1, 2, 3]), (second, [11, 12, 13])], SOURCE, "", None, engine)
    assert engine.rounds == [[1, 2, 11, 12], [13]]
    assert first.verdict == second.verdict == "missing: viscoelastic"
    assert (first.representatives, second.representatives) == ([1, 2], [11, 12, 13])


@pytest.mark.parametrize("texts, leads, chosen, want", [
    ([], [], 3, 2), (["a"], ["x"], 3, 1), (["a", "b"], ["x", "x"], 3, 1), (["a", "a"], ["x", "y"], 3, 1),
    ([], [], 1, 1), ([], [], 5, 3), (["a", "a"], ["x", "x"], 5, 1), (["a", "b"], ["", ""], 5, 2)])
def test_fewest_to_settle_is_the_missing_part_of_a_strict_majority(texts, leads, chosen, want):
    assert fewest_to_settle(texts, leads, chosen) == want
