#!/usr/bin/env python3
"""How much registration the search loses by answering with the wrong pose, and how well the
signals the server already computes would choose (issue: model v4, "what limits it").

Input: the `cases.json` of `cmr-agent eval --merge-duplicates false --record-hypotheses`, where
every start ran its whole trajectory and each recorded step carries what the policy said at the
pose before it (`value`, `policy_certainty`, `probabilities`, `action_indices`;
src/eval/learned.rs, `policy_step`). A candidate is any pose the search visited at which the
policy was evaluated (the start and every step but the last of each hypothesis), so every signal
is known for it at no extra cost. Registered: RTE < 5 m and RRE (Euler sum) < 10 deg (protocol A, `PoseError::registered`).

For each file it prints:
  oracle, any visited     share of cases with at least one registered candidate: the most any
                          choice among visited poses can register;
  oracle, any final       the same over the hypotheses' final poses (what the search answers from);
  judge J                 RR when the answer is the candidate that maximises J, and the mean
                          within-case AUC of J (registered vs not, over cases that have both).
Judges: the alignment score (what the server ranks hypotheses by), the policy's log-probability
of the zero step summed over the three DoF (`log_p_zero`: the agent's own "I am there"), the
critic's value, the policy certainty, alignment + lambda * log_p_zero, and (recordings with
`frustum_iou` per pose) the frustum IoU of `Confidence` alone and added to the alignment.
How the server's own search would answer under such a judge: `scripts/search-rules.py`.

    python3 scripts/pose-judges.py /tmp/rec/real-dev/cases.json /tmp/rec/synth-val/cases.json
"""

import argparse
import json
import math
from collections import defaultdict

RR_M, RR_DEG = 5.0, 10.0
LAMBDAS = [0.02, 0.05, 0.1, 0.2, 0.5, 1.0]


def registered(record):
    return record["rte_m"] < RR_M and record["rre_euler_deg"] < RR_DEG


def zero_index(probabilities):
    """The zero step sits in the middle of each DoF's ascending, symmetric step list."""
    return len(probabilities[0]) // 2


def candidates(path):
    """{case index: [candidate dicts]}, and the number of cases and of those with a registered
    final pose."""
    agent = [r for r in json.load(open(path)) if r["method"] == "cmr-agent"]
    by_case, final_ok = defaultdict(list), 0
    for case, record in enumerate(agent):
        hypotheses = record["notes"].get("hypotheses")
        if hypotheses is None:
            raise SystemExit(f"{path}: recorded without --record-hypotheses")
        finals = []
        for h in hypotheses:
            poses = [h["start"]] + h["steps"]
            finals.append(poses[-1])
            for pose, policy in zip(poses, h["steps"]):
                if "probabilities" not in policy:
                    raise SystemExit(f"{path}: recorded by a build without the policy's outputs per step")
                z = zero_index(policy["probabilities"])
                log_p_zero = sum(math.log(max(row[z], 1e-12)) for row in policy["probabilities"])
                by_case[case].append({
                    "registered": registered(pose),
                    "alignment": pose["alignment"],
                    "log_p_zero": log_p_zero,
                    "value": policy["value"],
                    "policy_certainty": policy["policy_certainty"],
                    "frustum_iou": pose.get("frustum_iou"),
                })
        final_ok += any(registered(p) for p in finals)
    return by_case, len(agent), final_ok


def judge(by_case, n, score):
    """(RR % of the argmax answer, mean within-case AUC)."""
    wins, aucs = 0, []
    for cands in by_case.values():
        scores = [score(c) for c in cands]
        wins += cands[max(range(len(cands)), key=scores.__getitem__)]["registered"]
        pos = [s for s, c in zip(scores, cands) if c["registered"]]
        neg = [s for s, c in zip(scores, cands) if not c["registered"]]
        if pos and neg:
            aucs.append(sum((p > q) + 0.5 * (p == q) for p in pos for q in neg) / (len(pos) * len(neg)))
    return 100.0 * wins / n, (sum(aucs) / len(aucs) if aucs else float("nan"))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases", nargs="+", help="cases.json of eval --merge-duplicates false --record-hypotheses")
    args = ap.parse_args()
    judges = [
        ("alignment", lambda c: c["alignment"]),
        ("log_p_zero", lambda c: c["log_p_zero"]),
        ("value", lambda c: c["value"]),
        ("policy_certainty", lambda c: c["policy_certainty"]),
    ] + [(f"alignment + {lam:g} log_p_zero", lambda c, lam=lam: c["alignment"] + lam * c["log_p_zero"]) for lam in LAMBDAS]
    iou_judges = [
        ("frustum_iou", lambda c: c["frustum_iou"]),
        ("alignment + 0.3 frustum_iou", lambda c: c["alignment"] + 0.3 * c["frustum_iou"]),
        ("alignment + 1 frustum_iou", lambda c: c["alignment"] + c["frustum_iou"]),
    ]
    for path in args.cases:
        by_case, n, final_ok = candidates(path)
        visited_ok = sum(any(c["registered"] for c in cands) for cands in by_case.values())
        print(f"{path}: {n} cases, {sum(map(len, by_case.values()))} candidates")
        print(f"  oracle, any visited   {100.0 * visited_ok / n:5.1f} %")
        print(f"  oracle, any final     {100.0 * final_ok / n:5.1f} %")
        has_iou = all(c["frustum_iou"] is not None for cands in by_case.values() for c in cands)
        for name, score in judges + (iou_judges if has_iou else []):
            rr, auc = judge(by_case, n, score)
            print(f"  {name:30s} RR {rr:5.1f} %   within-case AUC {auc:.3f}")


if __name__ == "__main__":
    main()
