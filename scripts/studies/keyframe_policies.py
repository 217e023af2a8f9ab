"""Which keyframe policy keeps a CPU up with a camera (docs/decisions.md, "Keyframes").

For one sequence: the windowed reference (``node_online`` with every frame a keyframe, each
frame waiting for the one before: the windows' accuracy at any speed) and ``no_ttr``; then per
``keyframe_policy`` the live output fed in real time at ``--rate`` (``sfm_ttr_live``) and the
windowed output as the node's keyframe rule makes it at that rate (``node_online`` in virtual
time). Prints and writes (``--out``/summary.json) the live output's share of the windowed gain,
(no_ttr - live) / (no_ttr - windowed), and the windowed accuracy of the frames the policy's
windows refined against the reference's on the same frames.

    .venv/bin/python scripts/studies/keyframe_policies.py --kitti-raw b300/raw \\
        --kitti-gt b300/gt --drive 2011_09_26_drive_0001_sync --rate 10 --out bench/kf_b300
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

from sfm_ttr_ros.tools.cli import main as sfm_ttr  # noqa: E402


def _bench(seq_args: list[str], out: Path, modes: list[str], extra: list[str]) -> dict:
    if not (out / "results.json").is_file():
        code = sfm_ttr(["benchmark", *seq_args, "--modes", *modes, "--out", str(out),
                        "--figure-frames", "0", *extra])
        if code != 0:
            raise SystemExit(f"sfm-ttr benchmark failed ({code}) for {out}")
    return json.loads((out / "results.json").read_text())


def _per_frame(out: Path, mode: str) -> dict[str, dict]:
    with open(out / "per_frame.csv") as fh:
        return {r["name"]: r for r in csv.DictReader(fh) if r.get(f"{mode}_abs_rel")}


def _share(no_ttr: float, live: float, windowed: float) -> float:
    gain = no_ttr - windowed
    return (no_ttr - live) / gain if gain > 0 else math.nan


def _covered(ref: dict[str, dict], run: dict[str, dict]) -> dict:
    """abs rel of the frames the run's windows refined, in the run and in the reference."""
    names = [n for n, r in run.items() if r["node_online_refined"] == "1" and n in ref]
    if not names:
        return {"frames": 0}
    mean = lambda rows, key: sum(float(r[key]) for r in rows) / len(rows)  # noqa: E731
    a = mean([run[n] for n in names], "node_online_abs_rel")
    b = mean([ref[n] for n in names], "node_online_abs_rel")
    return {"frames": len(names), "abs_rel": a, "reference_abs_rel": b, "ratio": a / b}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rate", type=float, default=10.0)
    ap.add_argument("--policies", nargs="+", default=["all", "newest"])
    ap.add_argument("--out", required=True)
    ap.add_argument("--set", action="append", default=[], help="passed to every run")
    args, seq_args = ap.parse_known_args(argv)
    out = Path(args.out)
    extra = [x for s in args.set for x in ("--set", s)]
    ref_out = out / "reference"
    ref = _bench(seq_args, ref_out, ["no_ttr", "node_online"],
                 extra + ["--set", "keyframe_policy=all"])
    no_ttr, windowed = ref["no_ttr"]["abs_rel"], ref["node_online"]["abs_rel"]
    rows = {"no_ttr": no_ttr, "windowed": windowed, "rate": args.rate, "policies": {}}
    for policy in args.policies:
        run_out = out / policy
        res = _bench(seq_args, run_out, ["node_online", "sfm_ttr_live"],
                     extra + ["--set", f"keyframe_policy={policy}", "--rate", str(args.rate),
                              "--node-rate", str(args.rate)])
        live = res["sfm_ttr_live"]
        rows["policies"][policy] = {
            "live_abs_rel": live["abs_rel"], "live_rmse": live["rmse"],
            "live_share": _share(no_ttr, live["abs_rel"], windowed),
            "live_share_rmse": _share(ref["no_ttr"]["rmse"], live["rmse"],
                                      ref["node_online"]["rmse"]),
            "live_latency_p95_s": live.get("latency_p95_s"),
            "live_windows": live.get("windows"), "live_windows_refined":
                live.get("windows_refined"),
            "dropped": live.get("stream_counters", {}).get("dropped_by_reason"),
            "windowed_covered": _covered(_per_frame(ref_out, "node_online"),
                                         _per_frame(run_out, "node_online")),
            "windowed_all_frames": res["node_online"]["abs_rel"]}
    (out / "summary.json").write_text(json.dumps(rows, indent=2) + "\n")
    print(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
