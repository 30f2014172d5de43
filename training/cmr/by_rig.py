"""Registration recall per rig from `cmr-agent eval`'s cases.json.

    python -m cmr.by_rig EVAL_OUT/cases.json --rigs RIGS.json
    python -m cmr.by_rig EVAL_OUT/cases.json --rigs real-dev

RIGS.json maps a sequence name to {"rig": NAME, ...} (`python -m cmr.real_split` writes one for
../shared/real-train, `OUT/rigs.json`); `real-dev` names the table of ../shared/real-dev/README.md
(00-06 KITTI object, 07-08 KITTI raw, 09 another vehicle rig). Prints, per rig and method, the
cases, RR (protocol A as `cmr-agent eval` counts it: `calibrate.registered`) and the mean RTE /
RRE (Euler sum) over the registered cases, as a Markdown table.
"""

from __future__ import annotations

import argparse
import collections
import json

from .calibrate import registered

REAL_DEV = {f"{i:02d}": "KITTI object" for i in range(7)} | {"07": "KITTI raw", "08": "KITTI raw", "09": "another rig (1920x1200)"}


def table(cases: list[dict], rig_of: dict[str, str]) -> list[str]:
    """Markdown rows (header first) of RR per (rig, method) over `cases` (cases.json records)."""
    groups = collections.defaultdict(list)
    for case in cases:
        groups[(rig_of.get(case["sequence"], "?"), case["method"])].append(case["errors"][-1])
    rows = ["| rig | method | cases | RR | RTE / RRE over registered |", "|---|---|---|---|---|"]
    for (rig, method), finals in sorted(groups.items()):
        ok = [f for f in finals if registered(f)]
        err = (f"{sum(f['rte_m'] for f in ok) / len(ok):.2f} m / {sum(f['rre_euler_deg'] for f in ok) / len(ok):.1f}°"
               if ok else "–")
        rows.append(f"| {rig} | {method} | {len(finals)} | {100 * len(ok) / len(finals):.1f} % ({len(ok)}) | {err} |")
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases")
    ap.add_argument("--rigs", required=True, help="sequence -> {rig} JSON, or 'real-dev'")
    args = ap.parse_args(argv)
    rig_of = REAL_DEV if args.rigs == "real-dev" else {s: v["rig"] for s, v in json.load(open(args.rigs)).items()}
    print("\n".join(table(json.load(open(args.cases)), rig_of)))


if __name__ == "__main__":
    main()
