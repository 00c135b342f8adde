"""What a fold job pays to open its campaign: a full read against the surrogate-vouched lazy open.

A fold job (`crashfuse fit`, `rollout`, `score` with `--surrogate`) needs the content hash of the
whole campaign and the pulses of the tests and their companion CAE runs only. Timed here, each the
best of ``--repeat`` runs, all in this process: ``full`` (every run parsed, the content hash
computed), ``lazy open`` (``read_campaign(known=...)``: the conditions parsed, the folder's bytes
hashed), ``lazy + tests`` (the open, then every test and its companion read, as a training fold
does), and the ratio full / (lazy + tests).

    .venv/bin/python benchmarks/bench_campaign_read.py CAMPAIGN [--repeat 5] [--json]
"""

from __future__ import annotations

import argparse
import json
import time

from crashfuse.io.campaign import read_campaign


def _best(fn, repeat: int) -> float:
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _fold_read(folder, known) -> None:
    campaign = read_campaign(folder, known=known)
    for test in campaign.tests:
        campaign.pulses[test], campaign.companion(test)


def measure(folder, repeat: int = 5) -> dict:
    """Seconds of each way of opening ``folder`` and the ratio (see the module docstring)."""
    whole = read_campaign(folder)
    known = (whole.source, whole.content_hash())
    lazy = read_campaign(folder, known=known)
    if lazy.content_hash() != known[1] or isinstance(lazy.pulses, dict):
        raise RuntimeError("the lazy open did not take: the folder changed while it was measured")
    out = {"runs": len(whole.pulses), "tests": len(whole.tests),
           "full_s": _best(lambda: read_campaign(folder).content_hash(), repeat),
           "lazy_open_s": _best(lambda: read_campaign(folder, known=known), repeat),
           "lazy_tests_s": _best(lambda: _fold_read(folder, known), repeat)}
    out["ratio"] = out["full_s"] / out["lazy_tests_s"]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("campaign", help="campaign folder")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--json", action="store_true", help="print the figures as JSON")
    args = ap.parse_args(argv)
    out = measure(args.campaign, args.repeat)
    if args.json:
        print(json.dumps(out))
        return 0
    print(f"{args.campaign}: {out['runs']} runs, {out['tests']} tests; best of {args.repeat}")
    print(f"  full read + content hash      {out['full_s']:.3f} s")
    print(f"  lazy open (known)             {out['lazy_open_s']:.3f} s")
    print(f"  lazy open + tests, companions {out['lazy_tests_s']:.3f} s")
    print(f"  ratio full / lazy + tests     {out['ratio']:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
