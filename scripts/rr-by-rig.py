#!/usr/bin/env python3
"""Registration recall per rig from `cmr-agent eval`'s cases.json (standard library only).

    python3 scripts/rr-by-rig.py EVAL_OUT/cases.json --rigs RIGS.json [--rr-deg 10 --rr-m 5]
    python3 scripts/rr-by-rig.py EVAL_OUT/cases.json --rigs real-dev

RIGS.json maps a sequence name to {"rig": NAME, ...} (`python -m cmr.real_split` writes one for
../shared/real-train, `OUT/rigs.json`); `real-dev` names the table of ../shared/real-dev/README.md
(00-06 KITTI object, 07-08 KITTI raw, 09 another vehicle rig). Prints, per rig and method, the
cases, RR (final pose's rotation error, the sum of absolute Euler angles, below --rr-deg and its
translation error below --rr-m: the paper's protocol A, as `cmr-agent eval` counts it) and the
mean RTE / RRE (Euler sum) over the registered cases, as a Markdown table.
"""
import argparse
import collections
import json

REAL_DEV = {f"{i:02d}": "KITTI object" for i in range(7)} | {"07": "KITTI raw", "08": "KITTI raw", "09": "another rig (1920x1200)"}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases")
    ap.add_argument("--rigs", required=True, help="sequence -> {rig} JSON, or 'real-dev'")
    ap.add_argument("--rr-deg", type=float, default=10.0)
    ap.add_argument("--rr-m", type=float, default=5.0)
    args = ap.parse_args()
    if args.rigs == "real-dev":
        rig_of = REAL_DEV
    else:
        rig_of = {seq: v["rig"] for seq, v in json.load(open(args.rigs)).items()}
    groups = collections.defaultdict(list)
    for case in json.load(open(args.cases)):
        final = case["errors"][-1] if isinstance(case["errors"], list) else case["errors"]
        groups[(rig_of.get(case["sequence"], "?"), case["method"])].append(final)
    print("| rig | method | cases | RR | RTE / RRE over registered |")
    print("|---|---|---|---|---|")
    for (rig, method), finals in sorted(groups.items()):
        ok = [f for f in finals if f["rre_euler_deg"] < args.rr_deg and f["rte_m"] < args.rr_m]
        err = (f"{sum(f['rte_m'] for f in ok) / len(ok):.2f} m / {sum(f['rre_euler_deg'] for f in ok) / len(ok):.1f}°"
               if ok else "–")
        print(f"| {rig} | {method} | {len(finals)} | {100 * len(ok) / len(finals):.1f} % ({len(ok)}) | {err} |")


if __name__ == "__main__":
    main()
