"""Two model sets on the same cases, case by case: the cases only one of them registers, and the
median RTE where both do (a paired comparison: two near-equal models differ by a few such cases,
far fewer than their totals' noise suggests).

    python -m cmr.paired A_EVAL_ROOT B_EVAL_ROOT NAME [NAME...]

Each NAME is an eval output folder under both roots (`cmr-agent eval --out ROOT/NAME`); the two
`cases.json` must hold the same cases in the same order (the same perturbation file). Registered
is protocol A on the served method's final answer (`calibrate.registered`: RTE < 5 m, RRE < 10°).
Prints a Markdown table, one row per NAME and a pooled row. ValueError when the cases differ.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

from .calibrate import registered

METHOD = "cmr-agent"


def finals(path: Path, method: str = METHOD) -> list[tuple[tuple[str, int], dict]]:
    """((sequence, frame), final error record) of `method`'s cases in a cases.json, in file order."""
    return [((c["sequence"], c["frame"]), c["errors"][-1]) for c in json.loads(path.read_text()) if c["method"] == method]


def compare(a: list, b: list) -> dict:
    """Counts of cases registered by A alone, B alone and both (lists from `finals`), with the
    median RTE (m) of each where both register (None when no case does)."""
    if [k for k, _ in a] != [k for k, _ in b]:
        raise ValueError("the two evaluations hold different cases")
    both = [(x["rte_m"], y["rte_m"]) for (_, x), (_, y) in zip(a, b) if registered(x) and registered(y)]
    return dict(cases=len(a), a=sum(registered(x) for _, x in a), b=sum(registered(y) for _, y in b),
                only_a=sum(registered(x) and not registered(y) for (_, x), (_, y) in zip(a, b)),
                only_b=sum(registered(y) and not registered(x) for (_, x), (_, y) in zip(a, b)), both=len(both),
                rte_a=statistics.median(p[0] for p in both) if both else None,
                rte_b=statistics.median(p[1] for p in both) if both else None)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", type=Path, help="root of model set A's eval outputs")
    ap.add_argument("b", type=Path, help="root of model set B's eval outputs")
    ap.add_argument("names", nargs="+", help="eval output folders under both roots")
    args = ap.parse_args(argv)
    fmt = lambda v: "–" if v is None else f"{v:.2f}"  # noqa: E731
    print("| eval | cases | A | B | only A / only B | median RTE where both (A / B, m) |\n|---|---|---|---|---|---|")
    pooled_a, pooled_b = [], []
    for name in args.names:
        a, b = finals(args.a / name / "cases.json"), finals(args.b / name / "cases.json")
        r = compare(a, b)
        pooled_a += [((name, *k), e) for k, e in a]
        pooled_b += [((name, *k), e) for k, e in b]
        print(f"| {name} | {r['cases']} | {r['a']} | {r['b']} | {r['only_a']} / {r['only_b']} | {fmt(r['rte_a'])} / {fmt(r['rte_b'])} |")
    r = compare(pooled_a, pooled_b)
    print(f"| **pooled** | {r['cases']} | {r['a']} | {r['b']} | {r['only_a']} / {r['only_b']} | {fmt(r['rte_a'])} / {fmt(r['rte_b'])} |")


if __name__ == "__main__":
    main()
