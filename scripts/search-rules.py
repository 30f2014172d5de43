#!/usr/bin/env python3
"""Replays the multi-start search on recorded trajectories to try rules that spend fewer policy
rows, before any of them is built into the server (issue: throughput, "spend less search").

Input: the `cases.json` of `cmr-agent eval --merge-duplicates false --record-hypotheses`, where
every start ran its whole trajectory (up to K steps or until the agent chose the zero step). A
rule only stops hypotheses earlier, and hypotheses do not influence each other's steps, so any
rule's search is a truncation of those trajectories and its answer can be replayed exactly: the
hypotheses that are still running after each step take one step (one policy row each), then the
server's duplicate merging (`src/agent/search.rs`: within DUPLICATE_M / DUPLICATE_DEG of an
earlier, not dropped hypothesis; `--duplicate M,DEG` replays another radius) and the rule under test stop some, and at the end the best alignment score wins (first
on ties). `--check` compares the replay of today's search with the answer the server gave
(`cmr-agent eval` without the two flags, its `cases.json`).

Rules (all measured against the alignment scores the server computes anyway while it builds the
next observation, so they cost no extra work):
  margin D after K: from step K on, a hypothesis whose current score is more than D below the
                    best current score stops (D = 0: only the leader goes on, `--narrow-after`).
  start margin D:   before the first step, starts scoring more than D below the best start stop.
  duplicates M / D: another duplicate radius (metres, degrees).
  converged leader D: once the best-scoring hypothesis has stopped on its own (zero step) and
                    leads every other by at least D, the others stop.
  running only:     duplicates count only against hypotheses still taking steps (one that
                    stopped short of the answer does not stop a later one that passes by).
  answer rules:     which pose the search answers with (the search itself as today): the best
                    final pose by alignment + w x frustum IoU, or the best of every pose visited
                    (recordings with `frustum_iou` per pose only: they cost the frustum head's
                    IoU, which the server computes for its answer's confidence anyway).

    python3 scripts/search-rules.py /tmp/rec/synth-val/cases.json /tmp/rec/real-dev/cases.json \
        [--check CASES_JSON_OF_TODAYS_SEARCH ... --duplicate 1,5]
"""

import argparse
import itertools
import json
import math

RR_DEG, RR_M = 10.0, 5.0
DUPLICATE = (4.0, 20.0)  # src/agent/search.rs: DUPLICATE_RTE_M, DUPLICATE_RRE_DEG


def pose(rows):
    """(R as 9 row-major values, t) from camera_from_map's row-major 3x4."""
    return [rows[4 * i + j] for i in range(3) for j in range(3)], [rows[3], rows[7], rows[11]]


def close(a, b, radius):
    """The server's duplicate test: PoseError::between(b, a) within radius = (metres, degrees
    geodesic)."""
    (ra, ta), (rb, tb) = a, b
    rte = math.dist(ta, tb)
    trace = sum(x * y for x, y in zip(ra, rb))  # trace(Rbᵀ Ra)
    cos = min(1.0, max(-1.0, (trace - 1.0) / 2.0))
    return rte < radius[0] and math.degrees(math.acos(cos)) < radius[1]


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


def alignment(state):
    """A recorded state's alignment score; -inf where none was recorded (never the answer)."""
    a = state["alignment"]
    return -math.inf if a is None or (isinstance(a, float) and math.isnan(a)) else a


def replay(case, iterations=10, merge=True, margin=None, after=1, start_margin=None, duplicate=DUPLICATE,
           converged_lead=None, only_running=False, iou_weight=0.0, visited=False):
    """(the answer's recorded state, policy rows). The answer is the final pose that scores best
    (alignment + `iou_weight` x frustum IoU; the server: weight 0), or with `visited` the best
    of every pose any start reached up to where it stopped."""
    hyps = case["hyps"]
    n = len(hyps)
    taken, dropped = [0] * n, [False] * n

    def done(h):
        full = len(hyps[h]["states"]) - 1
        return dropped[h] or taken[h] >= iterations or (taken[h] >= full)

    def score(h):
        return alignment(hyps[h]["states"][taken[h]])

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
                dropped[j] |= any(not dropped[i] and not (only_running and done(i))
                                  and close(pj, hyps[i]["poses"][taken[i]], duplicate) for i in range(j))
        if margin is not None and k >= after:
            best = max(score(h) for h in range(n))
            for h in range(n):
                if not done(h) and score(h) < best - margin:
                    dropped[h] = True
        if converged_lead is not None:
            scores = [score(h) for h in range(n)]
            leader = max(range(n), key=lambda h: (scores[h], -h))
            stopped = taken[leader] >= len(hyps[leader]["states"]) - 1 and hyps[leader]["converged"]
            if stopped and all(scores[leader] - scores[h] >= converged_lead for h in range(n) if h != leader):
                dropped = [d or h != leader for h, d in enumerate(dropped)]
    if iou_weight or visited:
        if iou_weight and any("frustum_iou" not in s for h in hyps for s in h["states"]):
            raise SystemExit("an IoU rule needs a recording with `frustum_iou` per pose (a build of 2026-12-01 or later)")
        answers = [s for h in range(n) for s in (hyps[h]["states"][:taken[h] + 1] if visited else [hyps[h]["states"][taken[h]]])]
        judged = [alignment(s) + iou_weight * s.get("frustum_iou", 0.0) for s in answers]
        return answers[max(range(len(answers)), key=lambda i: (judged[i], -i))], rows
    scores = [score(h) for h in range(n)]
    chosen = max(range(n), key=lambda h: (scores[h], -h))
    return hyps[chosen]["states"][taken[chosen]], rows


def registered(state):
    return state["rre_euler_deg"] < RR_DEG and state["rte_m"] < RR_M


def evaluate(cases, **rule):
    """(registered cases, policy rows per case, mean RTE and RRE (Euler) over the registered)."""
    hits, rows, rte, rre = 0, 0, 0.0, 0.0
    for c in cases:
        final, r = replay(c, **rule)
        if registered(final):
            hits += 1
            rte += final["rte_m"]
            rre += final["rre_euler_deg"]
        rows += r
    n = max(len(cases), 1)
    return hits, rows / n, rte / max(hits, 1), rre / max(hits, 1)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recorded", nargs="+", help="cases.json files of recorded runs (one per data set)")
    ap.add_argument("--check", nargs="*", default=[], help="cases.json of the same sets run with today's search")
    ap.add_argument("--duplicate", default=",".join(f"{v:g}" for v in DUPLICATE),
                    help="duplicate radius 'metres,degrees' of today's search (what --check ran with)")
    args = ap.parse_args()
    today = tuple(float(v) for v in args.duplicate.split(","))
    sets = [(p, load(p)) for p in args.recorded]
    for (path, cases), check in itertools.zip_longest(sets, args.check):
        if check is None:
            continue
        served = dict(enumerate(r for r in json.load(open(check)) if r["method"] == "cmr-agent"))
        same = sum(1 for c in cases if registered(replay(c, duplicate=today)[0]) == (served[c["key"]]["errors"][-1]["rre_euler_deg"] < RR_DEG
                                                                    and served[c["key"]]["errors"][-1]["rte_m"] < RR_M))
        print(f"check {path}: replay of today's search agrees with the server on {same}/{len(cases)} cases")
    rules = [(f"today (merge duplicates within {today[0]:g} m / {today[1]:g} deg)", dict(duplicate=today)),
             ("no merging", dict(merge=False))]
    rules += [(f"margin {d} after {k}", dict(margin=d, after=k)) for k in (1, 2, 3, 4) for d in (0.0, 0.02, 0.05, 0.1)]
    rules += [(f"start margin {d}", dict(start_margin=d)) for d in (0.05, 0.1, 0.2)]
    rules += [(f"duplicates within {m:g} m / {d:g} deg", dict(duplicate=(m, d)))
              for m, d in ((1, 5), (1, 10), (1, 25), (2, 10), (3, 15), (4, 20), (5, 25), (7, 35), (10, 50), (3, 30))]
    rules += [(f"converged leader {d} ahead stops the rest", dict(converged_lead=d)) for d in (0.0, 0.1)]
    rules += [(f"duplicates of running starts only, within {m:g} m / {d:g} deg", dict(duplicate=(m, d), only_running=True))
              for m, d in ((4, 20),)]
    if all("frustum_iou" in cases[0]["hyps"][0]["states"][0] for _, cases in sets if cases):
        rules += [(f"answer: best final pose by alignment + {w:g} frustum IoU", dict(iou_weight=w)) for w in (0.1, 0.3, 0.5, 1.0)]
        rules += [(f"answer: best visited pose by alignment + {w:g} frustum IoU", dict(iou_weight=w, visited=True)) for w in (0.0, 0.1, 0.3, 0.5, 1.0)]
    header = " | ".join(f"{p.split('/')[-2]} RR (rows/case) RTE m / RRE deg" for p, _ in sets)
    print(f"| rule | {header} |")
    print("|---|" + "---|" * len(sets))
    for name, rule in rules:
        cells = []
        for _, cases in sets:
            hits, rows, rte, rre = evaluate(cases, **rule)
            cells.append(f"{hits}/{len(cases)} ({rows:.1f}) {rte:.3f} / {rre:.2f}")
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
