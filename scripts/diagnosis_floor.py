"""The floor of the diagnosis' evidence on a campaign: what separates a test from its CAE rollout when no
effect is missing.

The diagnosis judges an effect by how much it lowers the held-out error of the CAE + effects rollout against
the measured pulse (docs/diagnosis.md). On a campaign whose CAE model misses nothing, that error is the
floor every effect must rise above. Per test with a companion CAE run this prints, as rms over the test's
record (in g), the difference from the companion run of:

- ``raw``: the measured record;
- ``body``: the record read back through the tests' measurement chain fitted on every test
  (:func:`crashfuse.method.model.fit_chain`, the mount the method's ``chain`` setting takes out; the record
  itself where the tests do not ring);
- ``rollout``: the diagnosis' own rollout of the CAE curve without effects, ``loading`` the same up to the
  rollout's turnaround (its largest crush) and ``after`` from there on;

and ``step``: how far the rollout's static CAE deceleration steps across the run's largest crush (between the
table's two nodes about it, g), where the reference changes to the faster CAE curve that a rollout crushing
further meets. Run from the project folder::

    .venv/bin/python scripts/diagnosis_floor.py CAMPAIGN
"""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd

from crashfuse.errors import InputError
from crashfuse.io.campaign import read_campaign
from crashfuse.method.effect_fit import DT, test_case
from crashfuse.method.laws import simulate
from crashfuse.method.model import fit_chain
from crashfuse.method.projection import cae_curve
from crashfuse.method.surrogate import CAESurrogate
from crashfuse.units import G0


def floor(campaign) -> pd.DataFrame:
    """One row per test with a companion run: ``raw``, ``body``, ``rollout``, ``loading``, ``after`` and
    ``step`` (g); empty when no test names one."""
    if all(campaign.companion(t) is None for t in campaign.tests):
        return pd.DataFrame()
    chain = fit_chain(campaign, campaign.tests)  # None: the tests do not ring, their body is their record
    surrogate = CAESurrogate(random_state=0).fit(campaign)
    case = test_case(campaign, surrogate)
    traj = simulate(case.plant, (), {}, DT, case.n_steps)
    rows = []
    for i, tid in enumerate(campaign.tests):
        test, cae = campaign.pulses[tid], campaign.companion(tid)
        if cae is None:
            continue
        inside = case.mask[i]
        ref, raw, body = (np.interp(case.time, p.time, a) for p, a in
                          ((cae, cae.decel), (test, test.decel),
                           (test, test.decel if chain is None else chain.body(test.time, test.decel))))
        turned = case.time >= case.time[np.argmax(traj.s[i])]
        curve = cae_curve(campaign, test, surrogate)
        cell = int(curve.s_max / case.plant.s_step)
        rest = case.plant.a_rest[i]
        miss = traj.decel[i] - ref
        rows.append({"test": tid, "raw": _rms(raw - ref, inside), "body": _rms(body - ref, inside),
                     "rollout": _rms(miss, inside), "loading": _rms(miss, inside & ~turned),
                     "after": _rms(miss, inside & turned),
                     "step": (rest[cell + 1] - rest[cell]) / G0})
    return pd.DataFrame(rows)


def _rms(x: np.ndarray, inside: np.ndarray) -> float:
    return float(np.sqrt(np.mean(x[inside] ** 2)) / G0) if inside.any() else float("nan")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("campaign")
    args = parser.parse_args(argv)
    try:
        table = floor(read_campaign(args.campaign))
    except InputError as err:
        raise SystemExit(f"diagnosis_floor: {err}") from None
    if table.empty:
        raise SystemExit(f"{args.campaign}: no test names a companion CAE run (cae_run_id)")
    print(table.to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    print("all tests (rms over tests): " + ", ".join(f"{c} {np.sqrt(np.mean(table[c] ** 2)):.3f} g"
                                                     for c in ("raw", "body", "rollout", "loading", "after")))


if __name__ == "__main__":
    main()
