#!/usr/bin/env python3
"""Replays the multi-start search on recorded trajectories to try rules that spend fewer policy
rows, before any of them is built into the server (issue: throughput, "spend less search").

Input: the `cases.json` of `cmr-agent eval --merge-duplicates false --record-hypotheses`, where
every start ran its whole trajectory (up to K steps or until the agent chose the zero step). A
rule only stops hypotheses earlier, and hypotheses do not influence each other's steps, so any
rule's search is a truncation of those trajectories and its answer can be replayed exactly: the
hypotheses that are still running after each step take one step (one policy row each), then the
server's duplicate merging (`src/agent/search.rs`: within 1 m / 5 deg of an earlier, not dropped
hypothesis) and the rule under test stop some, and at the end the best alignment score wins (first
on ties). `--check` compares the replay of today's search with the answer the server gave
(`cmr-agent eval` without the two flags, its `cases.json`).

Rules (all measured against the alignment scores the server computes anyway while it builds the
next observation, so they cost no extra work):
  margin D after K: from step K on, a hypothesis whose current score is more than D below the
                    best current score stops (D = 0: only the leader goes on, `--narrow-after`).
  start margin D:   before the first step, starts scoring more than D below the best start stop.

    python3 scripts/search-rules.py /tmp/rec/synth-val/cases.json /tmp/rec/real-dev/cases.json \
        [--check DIR_WITH_DEFAULT_CASES_JSON ...]
"""

import argparse
import itertools
import json
import math

import numpy as np

RR_DEG, RR_M = 10.0, 5.0
DUPLICATE_M, DUPLICATE_DEG = 1.0, 5.0


def pose(rows):
    m = np.array(rows, dtype=float).reshape(3, 4)
    return m[:, :3], m[:, 3]


def close(a, b):
    (ra, ta), (rb, tb) = a, b
    rte = np.linalg.norm(tb - ta)
    cos = np.clip((np.trace(rb.T @ ra) - 1.0) / 2.0, -1.0, 1.0)
    return rte < DUPLICATE_M and math.degrees(math.acos(cos)) < DUPLICATE_DEG


def load(path):
    cases = []
    for index, rec in enumerate(r for r in json.load(open(path)) if r["method"] == "cmr-agent"):
        if "hypotheses" not in rec.get("notes", {}):
            continue
        hyps = []
        for h in rec["notes"]["hypotheses"]:
            states = [h["start"]] + h["steps"]
            hyps.append(dict(states=states, poses=[pose(s["camera_from_map"]) for s in states], converged=h["converged"]))
        cases.append(dict(key=index, hyps=hyps))
    return cases


def replay(case, iterations=10, merge=True, margin=None, after=1, start_margin=None):
    """(final state of the chosen hypothesis, policy rows)."""
    hyps = case["hyps"]
    n = len(hyps)
    taken, dropped = [0] * n, [False] * n

    def done(h):
        full = len(hyps[h]["states"]) - 1
        return dropped[h] or taken[h] >= iterations or (taken[h] >= full)

    def score(h):
        a = hyps[h]["states"][taken[h]]["alignment"]
        return -math.inf if a is None or (isinstance(a, float) and math.isnan(a)) else a

    if start_margin is not None:
        best = max(score(h) for h in range(n))
        for h in range(n):
            dropped[h] = score(h) < best - start_margin
    rows = 0
    for k in range(1, iterations + 1):
        running = [h for h in range(n) if not done(h)]
        if not running:
            break
        for h in running:
            taken[h] += 1
        rows += len(running)
        if merge:
            for j in range(1, n):
                if done(j):
                    continue
                pj = hyps[j]["poses"][taken[j]]
                dropped[j] |= any(not dropped[i] and close(pj, hyps[i]["poses"][taken[i]]) for i in range(j))
        if margin is not None and k >= after:
            best = max(score(h) for h in range(n))
            for h in range(n):
                if not done(h) and score(h) < best - margin:
                    dropped[h] = True
    scores = [score(h) for h in range(n)]
    chosen = max(range(n), key=lambda h: (scores[h], -h))
    return hyps[chosen]["states"][taken[chosen]], rows


def registered(state):
    return state["rre_euler_deg"] < RR_DEG and state["rte_m"] < RR_M


def evaluate(cases, **rule):
    hits, rows = 0, 0
    for c in cases:
        final, r = replay(c, **rule)
        hits += registered(final)
        rows += r
    return hits, rows / max(len(cases), 1)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recorded", nargs="+", help="cases.json files of recorded runs (one per data set)")
    ap.add_argument("--check", nargs="*", default=[], help="cases.json of the same sets run with today's search")
    args = ap.parse_args()
    sets = [(p, load(p)) for p in args.recorded]
    for (path, cases), check in itertools.zip_longest(sets, args.check):
        if check is None:
            continue
        served = dict(enumerate(r for r in json.load(open(check)) if r["method"] == "cmr-agent"))
        same = sum(1 for c in cases if registered(replay(c)[0]) == (served[c["key"]]["errors"][-1]["rre_euler_deg"] < RR_DEG
                                                                    and served[c["key"]]["errors"][-1]["rte_m"] < RR_M))
        print(f"check {path}: replay of today's search agrees with the server on {same}/{len(cases)} cases")
    rules = [("today (merge duplicates)", {}), ("no merging", dict(merge=False))]
    rules += [(f"margin {d} after {k}", dict(margin=d, after=k)) for k in (1, 2, 3, 4) for d in (0.0, 0.02, 0.05, 0.1)]
    rules += [(f"start margin {d}", dict(start_margin=d)) for d in (0.05, 0.1, 0.2)]
    header = " | ".join(f"{p.split('/')[-2]} RR (rows/case)" for p, _ in sets)
    print(f"| rule | {header} |")
    print("|---|" + "---|" * len(sets))
    for name, rule in rules:
        cells = []
        for _, cases in sets:
            hits, rows = evaluate(cases, **rule)
            cells.append(f"{hits}/{len(cases)} ({rows:.1f})")
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
