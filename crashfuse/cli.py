"""The ``crashfuse`` command: argument parsing only; each subcommand calls the package.

Exit codes: 0 success, 2 bad input or arguments (one line on stderr), 1 anything else.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

from crashfuse.errors import InputError


class _Parser(argparse.ArgumentParser):
    """argparse that reports bad arguments as one InputError line (exit 2)."""

    def error(self, message):
        raise InputError(message, field="arguments")


def _print_json(obj) -> None:
    print(json.dumps(obj, indent=2, allow_nan=False))


# --- subcommands -----------------------------------------------------------------------


def _pulse_metrics(args) -> int:
    import pandas as pd

    from crashfuse.io.loading import load_pulses
    from crashfuse.metrics import pulse_metrics

    rows = [pulse_metrics(p) for p in load_pulses(args.path, cfc=None)]
    if args.json:
        _print_json(rows)
    else:
        print(pd.DataFrame(rows).to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    return 0


def _iso_score(args) -> int:
    from crashfuse.io.campaign import read_pulse_csv
    from crashfuse.iso18571 import iso_score
    from crashfuse.units import MS

    t_ref, ref = read_pulse_csv(args.test)
    t_cmp, cmp_ = read_pulse_csv(args.prediction)
    scores = iso_score(t_ref, ref, t_cmp, cmp_, start=args.start_ms * MS, end=args.end_ms * MS)
    if args.json:
        _print_json(scores)
    else:
        print("  ".join(f"{k}={v:.3f}" for k, v in scores.items()))
    return 0


def _world_generate(args) -> int:
    from crashfuse.world.effects import parse_overrides
    from crashfuse.world.generate import generate
    from crashfuse.world.presets import resolve

    design = resolve(args.preset, args.withhold, args.strength, parse_overrides(args.effect_param))
    folder = generate(args.out, design, seed=args.seed)
    print(f"wrote {folder} (preset {design.preset}, withheld {list(design.withheld)}, seed {args.seed})")
    return 0


def _world_calibrate(args) -> int:
    from crashfuse.world.calibrate import report

    print(report(args.nhtsa, refit=not args.check, max_nfev=args.max_evals))
    return 0


def _world_realism(args) -> int:
    from crashfuse.io.campaign import read_campaign
    from crashfuse.world.realism import report

    print(report(read_campaign(args.campaign)))
    return 0


# The real test sits beside the repository (../shared), never inside it.
_DEFAULT_NHTSA = os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "nhtsa", "v10146")


def _seed(text: str) -> int:
    """argparse type: an integer seed >= 0."""
    try:
        value = int(text)
    except ValueError:
        raise InputError(f"expected an integer seed >= 0, got {text!r}", field="--seed") from None
    if value < 0:
        raise InputError(f"expected an integer seed >= 0, got {text!r}", field="--seed")
    return value


def _build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="crashfuse", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    s = sub.add_parser("pulse-metrics", help="pulse metrics of every run in a campaign, NHTSA EV5 or ISO-MME folder")
    s.add_argument("path", help="campaign folder, NHTSA EV5 test folder or ISO-MME test folder")
    s.add_argument("--json", action="store_true", help="print a JSON list instead of a table")
    s.set_defaults(func=_pulse_metrics)

    s = sub.add_parser("iso-score", help="ISO/TS 18571 rating of a prediction against a test (pulse CSVs)")
    s.add_argument("test", help="reference pulse CSV (time_s, decel_g or decel_mps2)")
    s.add_argument("prediction", help="compared pulse CSV, same format")
    s.add_argument("--start-ms", type=float, default=0.0, help="window start in ms (default 0)")
    s.add_argument("--end-ms", type=float, default=60.0, help="window end in ms, inclusive (default 60)")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=_iso_score)

    w = sub.add_parser("world", help="the synthetic crash world (validation only)")
    wsub = w.add_subparsers(dest="world_command", required=True, parser_class=_Parser)
    s = wsub.add_parser("generate", help="write a synthetic campaign folder and its world.json answer key")
    s.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    s.add_argument("--seed", type=_seed, default=0, help="seed of the CAE design and the test noise (default 0)")
    s.add_argument("--preset", default=None, help="paper (default) or withheld (needs --withhold)")
    s.add_argument("--withhold", default=None, help="effect the tests carry and the CAE does not, or none")
    s.add_argument("--strength", default="realistic", help="realistic (default) or subtle")
    s.add_argument("--effect-param", action="append", default=[], metavar="NAME=VALUE",
                   help="set an effect parameter in SI, e.g. damping.c=2000 (repeatable)")
    s.set_defaults(func=_world_generate)
    s = wsub.add_parser("calibrate", help="fit the test simulator to NHTSA 10146 and print the side-by-side table")
    s.add_argument("nhtsa", nargs="?", default=_DEFAULT_NHTSA, help="NHTSA EV5 folder of test 10146")
    s.add_argument("--check", action="store_true", help="only compare the committed defaults, no fit")
    s.add_argument("--max-evals", type=int, default=60, help="simulator evaluations for the fit (default 60)")
    s.set_defaults(func=_world_calibrate)
    s = wsub.add_parser("realism", help="CAE-vs-test ISO 18571 and plausibility table of a generated campaign")
    s.add_argument("campaign", help="campaign folder")
    s.set_defaults(func=_world_realism)
    return p


def main(argv: list[str] | None = None) -> int:
    try:
        args = _build_parser().parse_args(argv)
        return args.func(args)
    except InputError as err:
        print(f"crashfuse: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as err:  # noqa: BLE001 - the documented exit code 1
        if os.environ.get("CRASHFUSE_DEBUG"):
            raise
        print(f"crashfuse: internal error: {type(err).__name__}: {err} (set CRASHFUSE_DEBUG=1 for a traceback)",
              file=sys.stderr)
        return 1
