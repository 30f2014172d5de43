"""Registration recall per rig from `cmr-agent eval`'s cases.json.

    python -m cmr.by_rig EVAL_OUT/cases.json --rigs RIGS.json
    python -m cmr.by_rig EVAL_OUT/cases.json --rigs real-dev

RIGS.json maps a sequence name to {"rig": NAME, ...} (`python -m cmr.real_split` writes one for
../shared/real-train, `OUT/rigs.json`); `real-dev` names the table of ../shared/real-dev/README.md
(00-06 KITTI object, 07-08 KITTI raw, 09 another vehicle rig). Prints, per rig and method, the
cases, RR (protocol A as `cmr-agent eval` counts it: `calibrate.registered`) and the mean RTE /
RRE (Euler sum) over the registered cases, as a Markdown table. With `--axes`, also where the
registered answers' camera centres lie from the truth's, per rig: along the truth's ground
heading and sideways (to its right), mean of the absolute offsets and the signed mean, from the
`answer_camera_from_map` / `truth_camera_from_map` notes `cmr-agent eval` writes (docs/evaluation.md,
"A continuous polish").
"""

from __future__ import annotations

import argparse
import collections
import json

import numpy as np

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


def camera_centre(camera_from_map: np.ndarray) -> np.ndarray:
    """The camera centre in the map frame (metres) of a camera_from_map [3, 4]: -Rᵀ t."""
    return -camera_from_map[:, :3].T @ camera_from_map[:, 3]


def axes(cases: list[dict], rig_of: dict[str, str], method: str = "cmr-agent") -> list[str]:
    """Markdown rows (header first): per rig, the registered answers' camera-centre offsets from
    the truth's along its ground heading and sideways (metres; mean |.| and signed mean)."""
    groups = collections.defaultdict(list)
    for case in cases:
        notes = case.get("notes", {})
        if case["method"] != method or not registered(case["errors"][-1]) or "answer_camera_from_map" not in notes:
            continue
        answer, truth = (np.asarray(notes[k], dtype=float).reshape(3, 4) for k in ("answer_camera_from_map", "truth_camera_from_map"))
        forward = truth[2, :3] * [1.0, 1.0, 0.0]  # the optical axis in the map, on the ground plane
        forward /= np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        offset = camera_centre(answer) - camera_centre(truth)
        groups[rig_of.get(case["sequence"], "?")].append((offset @ forward, offset @ right))
    rows = ["| rig | registered | along the heading, mean abs (signed) | sideways, mean abs (signed) |", "|---|---|---|---|"]
    for rig, v in sorted(groups.items()):
        a = np.asarray(v)
        rows.append(f"| {rig} | {len(a)} | {np.abs(a[:, 0]).mean():.2f} m ({a[:, 0].mean():+.2f}) | {np.abs(a[:, 1]).mean():.2f} m ({a[:, 1].mean():+.2f}) |")
    return rows


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("cases")
    ap.add_argument("--rigs", required=True, help="sequence -> {rig} JSON, or 'real-dev'")
    ap.add_argument("--axes", action="store_true", help="also the registered answers' offsets along the heading and sideways")
    args = ap.parse_args(argv)
    rig_of = REAL_DEV if args.rigs == "real-dev" else {s: v["rig"] for s, v in json.load(open(args.rigs)).items()}
    cases = json.load(open(args.cases))
    print("\n".join(table(cases, rig_of)))
    if args.axes:
        print()
        print("\n".join(axes(cases, rig_of)))


if __name__ == "__main__":
    main()
