"""The ``crashfuse`` command: argument parsing only; each subcommand calls the package.

Exit codes: 0 success, 2 bad input or arguments (one line on stderr), 1 anything else.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from crashfuse import forkserver
from crashfuse.catalogue import EFFECTS
from crashfuse.errors import InputError
from crashfuse.evaluation.iso_table import WINDOWS


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
    from crashfuse.signals.metrics import pulse_metrics

    lsdyna = {"lsdyna_source": args.lsdyna_source, "lsdyna_units": args.lsdyna_units, "mass_kg": args.mass_kg}
    rows = [pulse_metrics(p) for p in load_pulses(args.path, cfc=None, lsdyna=lsdyna)]
    if args.json:
        _print_json(rows)
    else:
        print(pd.DataFrame(rows).to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    return 0


def _iso_score(args) -> int:
    from crashfuse.io.rating import score_files

    scores = score_files(args.test, args.prediction, args.start_ms, args.end_ms)
    if args.json:
        _print_json(scores)
    else:
        print("  ".join(f"{k}={v:.3f}" for k, v in scores.items()))
    return 0


def _barrier_model(args) -> int:
    from crashfuse.world.barrier import barrier_campaign

    folder, comparison = barrier_campaign(args.ev5_dir, args.out, args.powertrain, args.drive)
    if args.json:
        _print_json(comparison)
    else:
        iso = "  ".join(f"ISO {w} {s['overall']:.3f}" for w, s in comparison["iso"].items())
        print(f"wrote {folder}: {comparison['test']} and its single-mass model {comparison['cae_run_id']}; {iso}")
    return 0


def _world_generate(args) -> int:
    if args.world == "multibody":
        return _world_generate_multibody(args)
    from crashfuse.world.effects import parse_overrides
    from crashfuse.world.generate import generate
    from crashfuse.world.presets import resolve

    if args.matrix != "table1" or args.n_tests is not None:
        raise InputError("the first world has the Table 1 matrix only; use --world multibody",
                         field="--matrix" if args.matrix != "table1" else "--n-tests")
    design = resolve(args.preset, args.withhold, args.strength, parse_overrides(args.effect_param))
    folder = generate(args.out, design, seed=args.seed, **({} if args.n_cae is None else {"n_cae": args.n_cae}))
    print(f"wrote {folder} (preset {design.preset}, withheld {list(design.withheld)}, seed {args.seed})")
    return 0


def _world_generate_multibody(args) -> int:
    from crashfuse.world.multibody.effects import parse_overrides
    from crashfuse.world.multibody.generate import generate
    from crashfuse.world.multibody.presets import N_CAE, resolve

    design = resolve(args.preset, args.withhold, args.strength, parse_overrides(args.effect_param))
    folder = generate(args.out, design, seed=args.seed, n_cae=args.n_cae or N_CAE, matrix=args.matrix,
                      n_tests=args.n_tests)
    print(f"wrote {folder} (world multibody, matrix {args.matrix}, preset {design.preset}, "
          f"withheld {list(design.withheld)}, seed {args.seed})")
    return 0


def _world_calibrate(args) -> int:
    if args.world == "multibody":
        from crashfuse.world.multibody.calibrate import report
    else:
        from crashfuse.world.calibrate import report

    budget = {} if args.max_evals is None else {"max_nfev": args.max_evals}  # else the world's own default
    print(report(args.nhtsa, refit=not args.check, **budget))
    return 0


def _world_realism(args) -> int:
    from crashfuse.io.campaign import read_campaign
    from crashfuse.world.realism import report

    print(report(read_campaign(args.campaign)))
    return 0


def _world_noise_control(args) -> int:
    from crashfuse.world.noise_control import NOISE_G, make_noise_control

    noise_g = NOISE_G if args.noise_g is None else args.noise_g
    folder = make_noise_control(args.campaign, args.out, args.seed, noise_g)
    print(f"wrote {folder}: the tests of {args.campaign} replaced by their CAE runs plus {noise_g:g} g rms of "
          f"CFC 60 noise (seed {args.seed})")
    return 0


def _world_validate(args) -> int:
    from crashfuse.world.validation import N_CAE, exactly_right, validate

    table = validate(args.out, effects=args.effects, strengths=args.strengths, seeds=args.seeds,
                     n_cae=args.n_cae or N_CAE, worlds=args.worlds, pairs=args.pairs, n_jobs=args.jobs)
    runs = table.drop_duplicates(["world", "withheld", "strength", "seed"])
    print(f"{int(runs['first_correct'].sum())}/{len(runs)} campaigns with a right first effect, "
          f"{int(exactly_right(runs).sum())} with exactly the withheld effects -> {args.out}")
    return 0


def _world_validate_method(args) -> int:
    from crashfuse.world.method_validation import DEFAULTS, QUICK, validate_method

    given = dict(worlds=args.worlds, withheld=args.withheld, strengths=args.strengths, seeds=args.seeds,
                 matrices=args.matrices, n_cae=args.n_cae, inputs=args.inputs, ks=args.k, n_samples=args.samples)
    base = QUICK if args.quick else DEFAULTS
    spread = {name: base[name] if value is None else value for name, value in given.items()}
    result = validate_method(args.out, work=args.work, random_state=args.seed, n_jobs=args.jobs,
                             auto=_auto_arg(args.auto), effects=_effects_arg(args.effects), windows=args.windows,
                             **spread)
    print(result.summary.to_string(index=False, float_format=lambda x: f"{x:.3f}"))
    return 0


def _method_settings(args) -> dict:
    """The MethodConfig settings of ``_add_method_options`` (None: the input mode's default)."""
    return dict(assignment=args.assignment, extra_inputs=args.extra_inputs, cae_decel=args.cae_decel,
                n_grid=args.n_grid, use_companion=args.use_companion, trend=args.trend, pooled=args.pooled,
                onset=args.onset, shrink=args.shrink, chain=args.chain, effects=_effects_arg(args.effects))


def _effects_arg(effects: list) -> str | tuple:
    """``--effects`` as ``MethodConfig.effects``: ``auto``, ``none`` or a tuple of effects."""
    return effects[0] if effects in (["auto"], ["none"]) else tuple(effects)


def _fit(args) -> int:
    from crashfuse.method.config import MethodConfig
    from crashfuse.method.model import fit_model

    config = MethodConfig(k=args.k, inputs=args.inputs, random_state=args.seed, **_method_settings(args))
    campaign, surrogate = _campaign_and_surrogate(args)
    model = fit_model(campaign, config, holdout=args.holdout, surrogate=surrogate,
                      pooled=_pooled_from(args, campaign, config, surrogate))
    model.save(args.out, surrogate_file=args.surrogate)  # with --surrogate the model refers to its file
    gps = {b: 0 if est is None else len(est.gps_) for b, est in model.bias_.items()}
    print(f"wrote {args.out}: K={args.k} {args.inputs} inputs, {len(model.training_tests)} training tests, "
          f"GPs per branch {gps}, campaign {model.campaign_hash[:12]}")
    if model.physics is not None:
        print(_physics_line(model.physics))
    return 0


def _pooled_from(args, campaign, config, surrogate):
    """The pooled GPs of the ``--pooled-from`` model (None without it), which must be this fit's fold
    with another K: the same campaign, holdout and settings."""
    import dataclasses

    from crashfuse.method.model import holdout_tests, load_model

    if not args.pooled_from:
        return None
    other = load_model(args.pooled_from, surrogate)
    held = sorted(holdout_tests(campaign, args.holdout))
    same = (other.campaign_hash == campaign.content_hash(), other.holdout == held,
            dataclasses.replace(other.config, k=config.k) == config)
    if not all(same):
        what = [name for name, ok in zip(("campaign", "holdout", "method settings"), same) if not ok]
        raise InputError(f"expected a model of this fit with another K; different: {', '.join(what)}",
                         args.pooled_from, "pooled_from")
    return other.all_rows_gps()


def _campaign_and_surrogate(args):
    """The campaign of ``args.campaign`` and the ``--surrogate`` file's CAE surrogate checked against it (None
    without one). A surrogate fitted on the unchanged folder spares parsing the runs a command does not use."""
    from crashfuse.io.campaign import read_campaign
    from crashfuse.method.model import load_surrogate

    surrogate = load_surrogate(args.surrogate) if args.surrogate else None
    campaign = read_campaign(args.campaign, known=surrogate and surrogate.campaign_identity())
    if surrogate is not None:
        surrogate.check_campaign(campaign, args.surrogate)  # another campaign's would skew every fold silently
    return campaign, surrogate


def _rollout(args) -> int:
    from crashfuse.evaluation.fold import ROLLOUT_SUFFIX, rollout_fold, write_rollout_facts
    from crashfuse.io.atomic import atomic_path
    from crashfuse.method.model import load_model

    campaign, surrogate = _campaign_and_surrogate(args)
    model = load_model(args.model, surrogate)
    if model.campaign_hash != campaign.content_hash():
        raise InputError(f"the model was fitted on another campaign ({model.campaign_hash[:12]})", args.model,
                         "campaign_hash")
    _known_test(campaign, args.test)
    pred, facts = rollout_fold(model, campaign, args.test, args.samples, args.band, args.inner)
    out = Path(args.out)
    with atomic_path(out / f"{args.test}_prediction.csv") as tmp:
        pred.frame().to_csv(tmp, index=False, float_format="%.6g")
    write_rollout_facts(out / f"{args.test}{ROLLOUT_SUFFIX}", facts)
    print(f"wrote {out}: {args.test} {facts['inputs']} {facts['model']}, {args.samples} samples, "
          f"{facts['metrics']['predict_seconds']:.1f} s")
    return 0


def _score(args) -> int:
    import pandas as pd

    from crashfuse.evaluation.fold import COVERAGE_COLUMNS, ROLLOUT_SUFFIX, cae_pulse, read_rollout_facts, score_fold
    from crashfuse.evaluation.iso_table import COLUMNS
    from crashfuse.evaluation.records import write_fold_json
    from crashfuse.io.atomic import atomic_path
    from crashfuse.io.prediction import read_prediction_csv

    campaign, folder = _test_campaign(args), Path(args.fold)
    facts = read_rollout_facts(folder / f"{args.test}{ROLLOUT_SUFFIX}")
    frame = read_prediction_csv(folder / f"{args.test}_prediction.csv")
    cae = None
    if not campaign.companion(args.test):  # the surrogate's curve, checked against the whole campaign
        cae = cae_pulse(*_campaign_and_surrogate(args), args.test)
    scored = score_fold(campaign, args.test, frame, facts, args.windows, cae)
    write_fold_json(folder / f"{args.test}.fold.json", scored["record"])
    for rows, columns, name in ((scored["cae_iso"] + scored["iso"], list(COLUMNS), "iso_table.csv"),
                                ([scored["coverage"]], COVERAGE_COLUMNS, "coverage.csv")):
        with atomic_path(Path(args.table_dir) / name) as tmp:
            pd.DataFrame(rows, columns=columns).to_csv(tmp, index=False, float_format="%.6g")
    last = scored["iso"][-1]
    print(f"{args.test} {facts['inputs']} {facts['model']}: ISO({last['window_ms']}) {last['overall']:.3f}, "
          f"coverage {scored['coverage']['coverage']:.2f}")
    return 0


def _auto(args) -> int:
    import shutil

    from crashfuse.evaluation.fold import ROLLOUT_SUFFIX, auto_facts, read_rollout_facts, write_rollout_facts
    from crashfuse.io.atomic import atomic_path

    paths = [Path(p) for p in args.facts]
    bad = [p for p in paths if not p.name.endswith(ROLLOUT_SUFFIX)]
    if bad:
        raise InputError(f"expected rollout facts files (*{ROLLOUT_SUFFIX})", bad[0], "facts")
    index, facts = auto_facts([read_rollout_facts(p) for p in paths], args.inputs)
    test, out = facts["test_id"], Path(args.out)
    with atomic_path(out / f"{test}_prediction.csv") as tmp:
        shutil.copyfile(paths[index].parent / f"{test}_prediction.csv", tmp)
    write_rollout_facts(out / f"{test}{ROLLOUT_SUFFIX}", facts)
    print(f"{test}: auto chose {facts['settings']['chosen']} ({facts['settings']['candidates']})")
    return 0


def _test_campaign(args):
    """The campaign of ``args.campaign`` with only the test ``args.test`` and its companion read."""
    from crashfuse.io.campaign import read_campaign

    campaign = read_campaign(args.campaign, runs=[args.test])
    _known_test(campaign, args.test)
    return campaign


def _auto_arg(value):
    """``--auto`` absent: False; alone: True (the default modes); with modes: those."""
    return False if value is None else (value or True)


def _known_test(campaign, test_id) -> None:
    if test_id not in campaign.tests:
        raise InputError(f"expected a test of the campaign ({', '.join(campaign.tests)}), got {test_id!r}",
                         campaign.root, "--test")


def _plot_prediction(args) -> int:
    from crashfuse.reporting.plots import plot_fold

    title = args.title
    if args.json:
        try:
            flags = json.loads(Path(args.json).read_text())["extrapolation"]
        except (OSError, ValueError, KeyError) as err:
            raise InputError(f"expected the JSON of 'crashfuse predict --json' ({err})", args.json, "extrapolation")
        words = {"v0": "speed", "front_weight": "front weight", "rear_weight": "rear weight", "crush": "crush",
                 "rebound": "rebound", "state": "crush-velocity path"}
        outside = [words.get(k, k) for k, v in flags.items() if v and k != "any"]
        if outside:  # a prediction beyond the tests says so where it is looked at
            title = f"{title or ''} - OUTSIDE the tests ({', '.join(outside)})".strip(" -")
    print(f"wrote {plot_fold(None, args.prediction, args.out, title=title)}")
    return 0


def _select(args) -> int:
    import shutil

    from crashfuse.io.atomic import atomic_path
    from crashfuse.io.campaign import read_campaign
    from crashfuse.method.model import load_model
    from crashfuse.method.selection import choose, inner_error

    campaign = read_campaign(args.campaign)
    models = [load_model(m) for m in args.models]
    if len({tuple(m.training_tests) for m in models}) != 1 or any(m.campaign_hash != campaign.content_hash()
                                                                     for m in models):
        raise InputError("expected models fitted on the same tests of this campaign", args.models[0], "models")
    order = sorted(range(len(models)), key=lambda i: (models[i].config.k, models[i].config.inputs))
    pick = choose([inner_error(models[i], campaign) for i in order])
    chosen = order[pick.index]
    with atomic_path(args.out) as tmp:
        shutil.copyfile(args.models[chosen], tmp)
    scores = ", ".join(f"{models[i].config.inputs} K{models[i].config.k}: {e:.4g}" for i, e in zip(order, pick.scores))
    print(f"wrote {args.out}: auto chose {args.models[chosen]} (inner error, (m/s^2)^2: {scores})")
    return 0


def _plot_fold(args) -> int:
    from crashfuse.reporting.plots import plot_fold

    test = _test_campaign(args).pulses[args.test].after_contact()
    print(f"wrote {plot_fold(test, args.prediction, args.out, title=args.title)}")
    return 0


def _physics_line(physics) -> str:
    """The hybrid's fitted laws in one line (parameters SI), with any fallback it took."""
    laws = ", ".join(f"{name}={value:.4g}" for name, value in physics.theta.items())
    notes = "".join(f"; {note}" for note in physics.notes)
    return f"effect laws: {' + '.join(physics.effects) or 'none'} ({laws or 'nothing fitted'}){notes}"


def _predict(args) -> int:
    from crashfuse.io.atomic import atomic_path
    from crashfuse.method.model import load_model, load_surrogate
    from crashfuse.method.rollout import predict
    from crashfuse.units import LB, MPH

    model = load_model(args.model, load_surrogate(args.surrogate) if args.surrogate else None)
    pred = predict(model, args.v0_mph * MPH, args.front_weight_lb * LB, args.rear_weight_lb * LB,
                   args.powertrain, args.drive, n_samples=args.samples, random_state=args.seed, band=args.band)
    with atomic_path(args.out) as tmp:
        pred.frame().to_csv(tmp, index=False, float_format="%.6g")
    if pred.extrapolation["any"]:
        where = [k for k, v in pred.extrapolation.items() if v and k != "any"]
        print(f"crashfuse: warning: outside the bias data ({', '.join(where)}): the band is wide there",
              file=sys.stderr)
    if args.json:
        _print_json({"metrics": pred.metrics, "extrapolation": pred.extrapolation, "n_samples": pred.n_samples,
                     "campaign_hash": model.campaign_hash,
                     "settings": {**model.config.as_dict(), "holdout": model.holdout},
                     "effect_laws": None if model.physics is None else
                     {"effects": list(model.physics.effects), "parameters_si": model.physics.theta,
                      "notes": model.physics.notes}})
    return 0


def _prepare(args) -> int:
    from crashfuse.io.campaign import read_campaign
    from crashfuse.method.model import save_surrogate
    from crashfuse.method.surrogate import CAESurrogate

    campaign = read_campaign(args.campaign)
    save_surrogate(CAESurrogate(random_state=args.seed).fit(campaign), args.out)
    print(f"wrote {args.out}: CAE surrogate of the {len(campaign.cae)} CAE runs, campaign "
          f"{campaign.content_hash()[:12]}")
    return 0


def _forkserver(args) -> int:
    forkserver.serve(args.address, while_stdin_open=args.while_stdin_open)
    return 0


def _evaluate(args) -> int:
    from crashfuse.evaluation.loto import evaluate
    from crashfuse.reporting.plots import plot_evaluation

    campaign, surrogate = _campaign_and_surrogate(args)
    result = evaluate(campaign, ks=args.k, inputs=args.inputs, out=args.out,
                      n_samples=args.samples, random_state=args.seed, n_jobs=args.jobs, surrogate=surrogate,
                      holdout=args.holdout, band=args.band, auto=_auto_arg(args.auto), windows=args.windows,
                      **_method_settings(args))
    plot_evaluation(result, args.out, campaign)
    iso = result.iso_table
    print(iso[iso["window_ms"] == args.windows[-1]].groupby(["inputs", "model"])["overall"].mean().round(3).to_string())
    return 0


def _diagnose(args) -> int:
    from crashfuse.diagnosis.diagnose import diagnose, write_diagnosis

    campaign, surrogate = _campaign_and_surrogate(args)
    diag = diagnose(campaign, effects=args.effects, threshold=args.threshold, alpha=args.alpha, move=args.move,
                    k=args.k, inputs=args.inputs, n_samples=args.samples, random_state=args.seed, surrogate=surrogate,
                    in_sample=args.in_sample, residual_model=not args.no_residual, n_jobs=args.jobs,
                    fold_models=_fold_models(args, campaign, surrogate))
    out = write_diagnosis(diag, args.out, campaign)
    print(f"verdict: {', '.join(diag.verdict) or 'none'} -> {out / 'diagnosis.md'}")
    return 0


def _fold_models(args, campaign, surrogate) -> dict | None:
    """``--fold-models`` by held-out test, each checked: this campaign, one held-out test, every test once,
    the K and input mode of ``--k`` and ``--inputs``, no effect laws."""
    from crashfuse.diagnosis.diagnose import residual_fold_problem
    from crashfuse.method.model import load_model

    if not args.fold_models:
        return None
    out = {}
    for path in args.fold_models:
        model = load_model(path, surrogate)
        if model.campaign_hash != campaign.content_hash():
            raise InputError(f"the model was fitted on another campaign ({model.campaign_hash[:12]})", path,
                             "campaign_hash")
        if len(model.holdout) != 1 or model.holdout[0] in out:
            raise InputError(f"expected one fold model per test, each fitted without its test; this one holds out "
                             f"{model.holdout}", path, "holdout")
        problem = residual_fold_problem(model.config, args.k, args.inputs)
        if problem:
            raise InputError(f"{problem} (--k, --inputs)", path, "config")
        out[model.holdout[0]] = model
    missing = [t for t in campaign.tests if t not in out]
    if missing:
        raise InputError(f"expected a fold model for every test; none for {missing}", args.fold_models[0], "holdout")
    return out


def _aggregate(args) -> int:
    from crashfuse.reporting.tables import aggregate_iso_tables

    frame = aggregate_iso_tables(args.tables, args.out)
    print(f"wrote {args.out}: {len(frame)} rows")
    return 0


def _report(args) -> int:
    from crashfuse.reporting.tables import write_tables

    for path in write_tables(args.iso_table, args.out, score=args.score):
        print(f"wrote {path}")
    return 0


def _plot_summary(args) -> int:
    from crashfuse.reporting.plots import plot_iso_summary

    print(f"wrote {plot_iso_summary(args.iso_table, args.out, window=args.window, score=args.score)}")
    return 0


def _track(args) -> int:
    from crashfuse.io.atomic import write_text
    from crashfuse.reporting.tracking import log_evaluation

    try:
        config = json.loads(args.config_json) if args.config_json else None
    except json.JSONDecodeError as err:
        raise InputError(f"expected JSON: {err}", field="--config-json") from None
    logged = log_evaluation(args.results, args.tracking_uri, config=config, project_dir=os.getcwd(),
                            fold_files=args.folds)
    if args.out:
        write_text(args.out, json.dumps(logged, indent=2, sort_keys=True) + "\n")
    print(f"logged {len(logged['folds'])} folds to {logged['tracking_uri']} ({logged['experiment_name']})")
    return 0


def _register(args) -> int:
    import pandas as pd

    from crashfuse.io.atomic import write_text
    from crashfuse.reporting.served import register_model

    try:
        example = pd.DataFrame(json.loads(args.conditions_json))
    except (json.JSONDecodeError, ValueError, TypeError) as err:
        raise InputError(f"expected a JSON list of conditions: {err}", field="--conditions-json") from None
    try:
        registered = register_model(args.model, args.surrogate, args.campaign_name, inputs=args.inputs,
                                    model=args.label, example=example, artifacts=args.artifacts,
                                    tracking_uri=args.tracking_uri, n_samples=args.samples, random_state=args.seed)
    except ValueError as err:  # a condition the served model could not take
        raise InputError(str(err), field="--conditions-json") from None
    if args.out:
        write_text(args.out, json.dumps(registered, indent=2, sort_keys=True) + "\n")
    print(f"registered {registered['model_uri']} (run {registered['run_id']}) in {registered['tracking_uri']}")
    return 0


def _positive(text: str) -> int:
    """argparse type: an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise InputError(f"expected an integer >= 1, got {text!r}", field="arguments")
    return value


def _add_windows_option(s) -> None:
    s.add_argument("--windows", nargs="+", default=list(WINDOWS), metavar="START-END",
                   help=f"ISO/TS 18571 windows in ms (default {' '.join(WINDOWS)}; e.g. 0-100 rates the rebound)")


def _add_band_option(s) -> None:
    s.add_argument("--band", choices=("test", "latent"), default="test",
                   help="reported deceleration band: where a new test is expected (default), or the bias "
                        "function's uncertainty alone")


def _add_method_options(s) -> None:
    s.add_argument("--seed", type=_seed, default=0, help="seed of the surrogate, bias models and draws (default 0)")
    s.add_argument("--assignment", choices=("select", "blend"), default="select",
                   help="cluster rule of the bias model (default select)")
    s.add_argument("--use-companion", action=argparse.BooleanOptionalAction, default=None,
                   help="predict a test's condition with its companion CAE run instead of the surrogate "
                        "(default: the input mode's, paper no, state yes)")
    s.add_argument("--extra-inputs", action=argparse.BooleanOptionalAction, default=None,
                   help="one-hot powertrain and drive among the bias inputs (default: the input mode's, paper no, "
                        "state yes)")
    s.add_argument("--cae-decel", choices=("none", "unloading", "both"), default=None,
                   help="the branches whose bias inputs include the CAE deceleration at each point (the crush "
                        "stage; default: the input mode's, paper none, state unloading)")
    s.add_argument("--n-grid", type=_positive, default=200, help="bias points per test per branch (default 200)")
    s.add_argument("--trend", choices=("zero", "constant", "linear"), default=None,
                   help="trend of the bias GPs (default: the input mode's, paper constant, state zero)")
    s.add_argument("--pooled", action=argparse.BooleanOptionalAction, default=None,
                   help="with K > 1, cluster GPs on the residual of one pooled GP (default: the input mode's, "
                        "paper no, state yes)")
    s.add_argument("--onset", action=argparse.BooleanOptionalAction, default=None,
                   help="correct the bias model's held-out error over the time since contact in the first 22 ms "
                        "(state inputs only; default: off)")
    s.add_argument("--shrink", action=argparse.BooleanOptionalAction, default=None,
                   help="scale the bias mean, over the time since contact, by how well the training tests' "
                        "held-out predictions predict them (state inputs only; default: on for state)")
    s.add_argument("--chain", action=argparse.BooleanOptionalAction, default=None,
                   help="fit the tests' accelerometer mount resonance between the tests and their CAE runs, "
                        "learn the bias of the tests' body decelerations and read the rollout through the mount "
                        "(default: on for state)")
    s.add_argument("--effects", nargs="+", default=["none"], metavar="EFFECT",
                   help="physics-first hybrid: effect laws fitted to the training tests and added to the CAE "
                        f"model before the bias is learnt - auto (chosen on the training tests), none (default) "
                        f"or effects among: {' '.join(EFFECTS)}")


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
    for add in (_add_pulse_metrics, _add_iso_score, _add_barrier_model, _add_world, _add_fit, _add_predict,
                _add_rollout, _add_auto, _add_select, _add_score, _add_evaluate, _add_diagnose, _add_prepare, _add_aggregate, _add_report,
                _add_plot, _add_track, _add_register, _add_forkserver):
        add(sub)
    return p


# --- one parser per subcommand (in the order of `crashfuse --help`) ------------------------------


def _add_campaign(s) -> None:
    s.add_argument("campaign", help="campaign folder")


def _add_surrogate_option(s) -> None:
    s.add_argument("--surrogate", default=None,
                   help="CAE surrogate file (.cfmodel) from 'crashfuse prepare' (default: fit it)")


def _add_iso_table(s) -> None:
    s.add_argument("iso_table", help="iso_table.csv or the folder holding it")


def _add_pulse_metrics(sub) -> None:
    s = sub.add_parser("pulse-metrics", help="pulse metrics of every run in a campaign, NHTSA EV5 or ISO-MME folder "
                                             "or LS-DYNA binout")
    s.add_argument("path", help="campaign folder, NHTSA EV5 test folder, ISO-MME test folder or LS-DYNA binout")
    s.add_argument("--json", action="store_true", help="print a JSON list instead of a table")
    s.add_argument("--lsdyna-source", metavar="SOURCE",
                   help="binout only: rwforc[:<wall id>], matsum:<part id> or nodout:<node id>[:velocity]")
    s.add_argument("--lsdyna-units", metavar="L-T-M", help="binout only: the model's unit system, e.g. mm-ms-kg")
    s.add_argument("--mass-kg", type=float, help="binout only: the run's mass in kg")
    s.set_defaults(func=_pulse_metrics)


def _add_iso_score(sub) -> None:
    s = sub.add_parser("iso-score", help="ISO/TS 18571 rating of a prediction against a test (pulse CSVs)")
    s.add_argument("test", help="reference pulse CSV (time_s, decel_g or decel_mps2)")
    s.add_argument("prediction", help="compared pulse CSV, same format")
    s.add_argument("--start-ms", type=float, default=0.0, help="window start in ms (default 0)")
    s.add_argument("--end-ms", type=float, default=60.0, help="window end in ms, inclusive (default 60)")
    s.add_argument("--json", action="store_true", help="print JSON")
    s.set_defaults(func=_iso_score)


def _add_barrier_model(sub) -> None:
    s = sub.add_parser("barrier-model", help="single-mass model of a load-cell barrier test as its companion CAE run")
    s.add_argument("ev5_dir", metavar="EV5DIR", help="NHTSA EV5 test folder with barrier load cells")
    s.add_argument("--out", required=True, help="campaign folder to write (must not exist or be empty)")
    s.add_argument("--powertrain", default="unknown", help="powertrain label of both runs (default unknown)")
    s.add_argument("--drive", default="unknown", help="drive label of both runs (default unknown)")
    s.add_argument("--json", action="store_true", help="print the model-vs-test comparison as JSON")
    s.set_defaults(func=_barrier_model)


def _add_world_option(s) -> None:
    s.add_argument("--world", choices=("first", "multibody"), default="first",
                   help="first (default: one mass, staged crush law) or multibody (three masses, "
                        "folding-wave crush zone)")


def _add_world(sub) -> None:
    w = sub.add_parser("world", help="the synthetic crash world (validation only)")
    wsub = w.add_subparsers(dest="world_command", required=True, parser_class=_Parser)
    for add in (_add_world_generate, _add_world_calibrate, _add_world_realism, _add_world_noise_control,
                _add_world_validate, _add_world_validate_method):
        add(wsub)


def _add_world_generate(wsub) -> None:
    s = wsub.add_parser("generate", help="write a synthetic campaign folder and its world.json answer key")
    s.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    s.add_argument("--seed", type=_seed, default=0, help="seed of the CAE design and the test noise (default 0)")
    s.add_argument("--preset", default=None, help="paper (default) or withheld (needs --withhold)")
    _add_world_option(s)
    s.add_argument("--matrix", choices=("table1", "wide"), default="table1",
                   help="test matrix: the paper's Table 1 (default) or 11 tests over 10-37 mph (multibody only)")
    s.add_argument("--n-tests", type=_positive, default=None,
                   help="with --matrix wide: that many tests evenly spaced over 10-37 mph (a test library)")
    s.add_argument("--withhold", nargs="+", default=None, metavar="EFFECT",
                   help="effect(s) the tests carry and the CAE does not, or none")
    s.add_argument("--strength", default="realistic", help="realistic (default) or subtle")
    s.add_argument("--n-cae", type=_positive, default=None,
                   help="Latin-hypercube CAE runs (default 1009; multibody 400)")
    s.add_argument("--effect-param", action="append", default=[], metavar="NAME=VALUE",
                   help="set an effect parameter in SI, e.g. damping.c=2000 (repeatable)")
    s.set_defaults(func=_world_generate)


def _add_world_calibrate(wsub) -> None:
    s = wsub.add_parser("calibrate", help="fit the test simulator to NHTSA 10146 and print the side-by-side table")
    s.add_argument("nhtsa", nargs="?", default=_DEFAULT_NHTSA, help="NHTSA EV5 folder of test 10146")
    _add_world_option(s)
    s.add_argument("--check", action="store_true", help="only compare the committed defaults, no fit")
    s.add_argument("--max-evals", type=int, default=None,
                   help="simulator evaluations for the fit (default: first 60, multibody 80)")
    s.set_defaults(func=_world_calibrate)


def _add_world_realism(wsub) -> None:
    s = wsub.add_parser("realism", help="CAE-vs-test ISO 18571 and plausibility table of a generated campaign")
    _add_campaign(s)
    s.set_defaults(func=_world_realism)


def _add_world_noise_control(wsub) -> None:
    s = wsub.add_parser("noise-control", help="a campaign's noise control: its tests replaced by their CAE runs "
                                              "plus filtered measurement noise (docs/method-validation.md)")
    _add_campaign(s)
    s.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    s.add_argument("--seed", type=_seed, default=0, help="seed of the noise (default 0)")
    s.add_argument("--noise-g", type=float, default=None,
                   help="noise in g rms after CFC 60 (default: what NHTSA 10146's accelerometers read before contact)")
    s.set_defaults(func=_world_noise_control)


def _add_world_validate(wsub) -> None:
    s = wsub.add_parser("validate", help="withheld-effect validation of the gap diagnosis (reads world.json)")
    s.add_argument("--effects", nargs="+", default=list(EFFECTS), metavar="EFFECT",
                   help="effects withheld one at a time (the control with none is always added)")
    s.add_argument("--strengths", nargs="+", choices=("realistic", "subtle"), default=["realistic", "subtle"])
    s.add_argument("--seeds", nargs="+", type=_seed, default=[0], help="world seeds (default 0)")
    s.add_argument("--worlds", nargs="+", choices=("first", "multibody"), default=["first"],
                   help="worlds whose campaigns are diagnosed (default first; multibody scores the verdict only)")
    s.add_argument("--pairs", action="store_true",
                   help="also withhold every pair of the effects together")
    s.add_argument("--n-cae", type=_positive, default=None,
                   help="CAE runs per campaign besides the companions (default: the harness's N_CAE)")
    s.add_argument("--jobs", type=_positive, default=1,
                   help="campaigns generated and diagnosed at once (worker processes, default 1)")
    s.add_argument("--out", required=True, help="output folder for validation.csv and validation.md")
    s.set_defaults(func=_world_validate)


def _add_world_validate_method(wsub) -> None:
    s = wsub.add_parser("validate-method", help="method validation matrix: leave-one-test-out evaluation on "
                                                "campaigns of both worlds (docs/method-validation.md)")
    s.add_argument("--out", required=True, help="output folder for method_matrix.csv/.md and method_summary.csv")
    s.add_argument("--work", default=None,
                   help="folder of the generated campaigns and their evaluations, reused when present "
                        "(default OUT/work)")
    s.add_argument("--quick", action="store_true",
                   help="a tiny spread (the control of both worlds, seed 0, Table 1, 20 CAE runs, state K1, "
                        "20 samples); options given beside it still apply")
    s.add_argument("--worlds", nargs="+", default=None, help="first multibody (default both)")
    s.add_argument("--withheld", nargs="+", default=None, metavar="WITHHELD",
                   help="single (every effect), pairs (every pair), paper, none (the control), "
                        "noise (the control with an exact CAE model: tests are their CAE runs plus noise), "
                        "an EFFECT or EFFECT+EFFECT (default: single pairs paper none noise)")
    s.add_argument("--strengths", nargs="+", default=None, help="realistic subtle (default both)")
    s.add_argument("--seeds", nargs="+", type=_seed, default=None, help="world seeds (default 0 1 2)")
    s.add_argument("--matrices", nargs="+", default=None,
                   help="table1 wide (default both; the first world has table1 only)")
    s.add_argument("--n-cae", nargs="+", type=_positive, default=None, help="CAE design sizes (default 150 1000)")
    s.add_argument("--inputs", nargs="+", default=None, help="input modes paper state (default state)")
    s.add_argument("--k", type=_positive, nargs="+", default=None, help="mixture sizes (default 1 2 3)")
    s.add_argument("--samples", type=_positive, default=None, help="Monte Carlo samples per fold (default 200)")
    s.add_argument("--auto", nargs="*", choices=("paper", "state"), default=None, metavar="MODE",
                   help="also the auto model, chosen among K (and the input modes MODE; default state)")
    s.add_argument("--effects", nargs="+", default=["none"], metavar="EFFECT",
                   help="the physics-first hybrid of every fold, as evaluate's --effects: auto, none (default) "
                        f"or effects among: {' '.join(EFFECTS)}")
    _add_windows_option(s)
    s.add_argument("--seed", type=_seed, default=0, help="seed of every evaluation (default 0)")
    s.add_argument("--jobs", type=_positive, default=2, help="worker processes for each campaign's folds (default 2)")
    s.set_defaults(func=_world_validate_method)


def _add_fit(sub) -> None:
    s = sub.add_parser("fit", help="fit the CAE surrogate and the per-branch bias models; write a model file")
    _add_campaign(s)
    s.add_argument("--k", type=_positive, required=True, help="mixture components K of the bias models")
    s.add_argument("--inputs", choices=("paper", "state"), default="paper",
                   help="bias inputs: paper [x, v0, w_f, w_r] or state [x, v, v0, w_f, w_r] (default paper)")
    s.add_argument("--holdout", action="append", default=None, metavar="RUN_ID",
                   help="test to keep out of the bias data (repeatable)")
    _add_surrogate_option(s)
    _add_method_options(s)
    s.add_argument("--pooled-from", metavar="MODEL",
                   help="model file of this fit with another K (same campaign, holdout and settings): "
                        "its pooled GP is reused, the same fit, not refitted")
    s.add_argument("--out", required=True, help="model file to write (e.g. model.cfmodel)")
    s.set_defaults(func=_fit)


def _add_rollout(sub) -> None:
    s = sub.add_parser("rollout", help="a fold's rollout: its held-out test's condition predicted by a model "
                                       "fitted without it (prediction CSV and the rollout's facts)")
    s.add_argument("model", help="model file (.cfmodel) from 'crashfuse fit --holdout TEST'")
    _add_campaign(s)
    s.add_argument("--test", required=True, help="the held-out test")
    s.add_argument("--samples", type=_positive, default=1000, help="Monte Carlo samples (default 1000)")
    s.add_argument("--inner", action="store_true", help="also the model's inner error (what --auto chooses by)")
    _add_surrogate_option(s)
    _add_band_option(s)
    s.add_argument("--out", required=True,
                   help="fold folder for <test>_prediction.csv and <test>.rollout.json")
    s.set_defaults(func=_rollout)


def _add_auto(sub) -> None:
    s = sub.add_parser("auto", help="the auto model's fold: of one test's candidate rollouts, the one with the "
                                    "smallest inner error (simplest first)")
    s.add_argument("facts", nargs="+", help="the candidates' <test>.rollout.json files (from 'rollout --inner')")
    s.add_argument("--inputs", nargs="+", choices=("paper", "state"), default=["state"],
                   help="the candidates' input modes, in order among candidates of one K (default state)")
    s.add_argument("--out", required=True, help="fold folder for the chosen <test>_prediction.csv and facts")
    s.set_defaults(func=_auto)


def _add_select(sub) -> None:
    s = sub.add_parser("select", help="the auto model file: of models fitted on the same tests, the one of the "
                                      "smallest inner error (simplest first)")
    _add_campaign(s)
    s.add_argument("models", nargs="+", help="model files (.cfmodel) from 'crashfuse fit' on this campaign")
    s.add_argument("--out", required=True, help="the chosen model, copied here")
    s.set_defaults(func=_select)


def _add_score(sub) -> None:
    s = sub.add_parser("score", help="a fold's ISO/TS 18571 rows, band coverage and fold JSON from its rollout")
    _add_campaign(s)
    s.add_argument("fold", help="fold folder holding <test>_prediction.csv and <test>.rollout.json")
    s.add_argument("--test", required=True, help="the held-out test")
    _add_windows_option(s)
    _add_surrogate_option(s)
    s.add_argument("--table-dir", required=True, help="folder for the fold's iso_table.csv and coverage.csv")
    s.set_defaults(func=_score)


def _add_predict(sub) -> None:
    s = sub.add_parser("predict", help="bias-corrected pulse with a 95 %% Monte Carlo band at one condition")
    s.add_argument("model", help="model file (.cfmodel) from 'crashfuse fit'")
    s.add_argument("--v0-mph", type=float, required=True, help="impact speed, mph")
    s.add_argument("--front-weight-lb", type=float, required=True, help="front axle weight, lb")
    s.add_argument("--rear-weight-lb", type=float, required=True, help="rear axle weight, lb")
    s.add_argument("--powertrain", default=None, help="powertrain label (when the model uses it)")
    s.add_argument("--drive", default=None, help="drive label (when the model uses it)")
    s.add_argument("--samples", type=_positive, default=1000, help="Monte Carlo samples (default 1000)")
    s.add_argument("--seed", type=_seed, default=0, help="seed of the draws (default 0)")
    s.add_argument("--out", required=True, help="prediction CSV to write")
    s.add_argument("--json", action="store_true", help="print the pulse metrics with bands as JSON")
    s.add_argument("--surrogate", default=None,
                   help="the CAE surrogate file a model fitted with --surrogate refers to (default: the file it names)")
    _add_band_option(s)
    s.set_defaults(func=_predict)


def _add_evaluate(sub) -> None:
    s = sub.add_parser("evaluate", help="leave-one-test-out ISO/TS 18571 table, predictions and band coverage")
    _add_campaign(s)
    s.add_argument("--k", type=_positive, nargs="+", default=[1, 2, 3], help="mixture sizes (default 1 2 3)")
    s.add_argument("--inputs", choices=("paper", "state"), nargs="+", default=["paper", "state"],
                   help="input modes (default both)")
    s.add_argument("--samples", type=_positive, default=1000, help="Monte Carlo samples per fold (default 1000)")
    s.add_argument("--jobs", type=_positive, default=2, help="worker processes (default 2)")
    s.add_argument("--holdout", action="append", default=None, metavar="RUN_ID",
                   help="run only the fold holding out this test (repeatable; default every test)")
    s.add_argument("--auto", nargs="*", choices=("paper", "state"), default=None, metavar="MODE",
                   help="also the auto model: per fold, the K (and input mode, among MODE; default state) of the "
                        "smallest inner error on the training tests (rows labelled auto)")
    _add_surrogate_option(s)
    _add_method_options(s)
    _add_band_option(s)
    _add_windows_option(s)
    s.add_argument("--out", required=True, help="output folder")
    s.set_defaults(func=_evaluate)


def _add_diagnose(sub) -> None:
    s = sub.add_parser("diagnose", help="sim-to-real gap: where it lies, which unmodelled effect, how far it shrinks")
    _add_campaign(s)
    s.add_argument("--effects", nargs="+", default=list(EFFECTS), metavar="EFFECT",
                   help=f"candidate effects (default all: {' '.join(EFFECTS)})")
    s.add_argument("--threshold", type=float, default=0.10,
                   help="relative drop of the held-out squared error an effect must bring (default 0.10)")
    s.add_argument("--alpha", type=float, default=0.125,
                   help="level of the one-sided sign test over the folds an effect acts on (default 0.125)")
    s.add_argument("--move", type=float, default=0.05,
                   help="an effect acts on a fold when it moves the held-out prediction by more than this "
                        "share of the test's rms deceleration (default 0.05)")
    s.add_argument("--k", type=_positive, default=1,
                   help="mixture size of the bias model of the gap map and the GMM-GPR rows (default 1)")
    s.add_argument("--samples", type=_positive, default=200, help="Monte Carlo samples per GMM-GPR fold (default 200)")
    s.add_argument("--inputs", choices=("paper", "state"), default="state",
                   help="bias inputs of the GMM-GPR rows (default state, the method's default)")
    _add_surrogate_option(s)
    s.add_argument("--seed", type=_seed, default=0, help="seed (default 0)")
    s.add_argument("--in-sample", action="store_true", help="allow a single test (no hold-out; evidence in-sample)")
    s.add_argument("--no-residual", action="store_true", help="skip the GMM-GPR rows of the shrink table (faster)")
    s.add_argument("--fold-models", nargs="+", metavar="MODEL",
                   help="the GMM-GPR alone's fold models, one per test fitted without it with --k and --inputs "
                        "(e.g. the workflow's): rolled out instead of refitted, their settings used for the "
                        "CAE + effects + GMM-GPR folds")
    s.add_argument("--jobs", type=_positive, default=2,
                   help="worker processes for a round's candidate effects and the shrink table's GMM-GPR "
                        "folds (default 2)")
    s.add_argument("--out", required=True, help="output folder")
    s.set_defaults(func=_diagnose)


def _add_prepare(sub) -> None:
    s = sub.add_parser("prepare", help="fit the CAE surrogate once on a campaign's CAE runs (shared by folds)")
    _add_campaign(s)
    s.add_argument("--seed", type=_seed, default=0, help="seed of the surrogate's fit (default 0)")
    s.add_argument("--out", required=True, help="surrogate file to write (e.g. surrogate.cfmodel)")
    s.set_defaults(func=_prepare)


def _add_forkserver(sub) -> None:
    s = sub.add_parser("forkserver", help="serve commands from one process that imported the package once (the "
                       "workflow's warm start; commands with CRASHFUSE_FORKSERVER=ADDRESS use it)")
    s.add_argument("address", help="path of the Unix socket to listen at")
    s.add_argument("--while-stdin-open", action="store_true",
                   help="stop when standard input closes (started on a pipe: ends with the process that started it)")
    s.set_defaults(func=_forkserver)


def _add_aggregate(sub) -> None:
    s = sub.add_parser("aggregate", help="combine per-fold ISO tables into one iso_table.csv (CAE rows once)")
    s.add_argument("tables", nargs="+", help="per-fold iso_table.csv files")
    s.add_argument("--out", required=True, help="combined iso_table.csv")
    s.set_defaults(func=_aggregate)


def _add_report(sub) -> None:
    s = sub.add_parser("report", help="the paper's Table 2 (Markdown, LaTeX) and the summary from iso_table.csv")
    _add_iso_table(s)
    s.add_argument("--out", required=True, help="output folder")
    s.add_argument("--score", default="overall", help="score shown in Table 2 (default overall)")
    s.set_defaults(func=_report)


def _add_plot(sub) -> None:
    s = sub.add_parser("plot", help="figures")
    psub = s.add_subparsers(dest="plot_command", required=True, parser_class=_Parser)
    s = psub.add_parser("summary", help="ISO score by test and K, per input mode")
    _add_iso_table(s)
    s.add_argument("--window", default="0-60", help="window label, e.g. 0-60 (default)")
    s.add_argument("--score", default="overall", help="score to plot (default overall)")
    s.add_argument("--out", required=True, help="PNG file")
    s.set_defaults(func=_plot_summary)
    s = psub.add_parser("prediction", help="a prediction's CAE and corrected pulse with its band (no test)")
    s.add_argument("prediction", help="the prediction CSV ('crashfuse predict')")
    s.add_argument("--json", default=None, help="its 'crashfuse predict --json' output: an extrapolation goes in the title")
    s.add_argument("--title", default=None, help="figure title")
    s.add_argument("--out", required=True, help="PNG file")
    s.set_defaults(func=_plot_prediction)
    s = psub.add_parser("fold", help="a fold's test, CAE and corrected pulse with its band")
    _add_campaign(s)
    s.add_argument("prediction", help="the fold's prediction CSV")
    s.add_argument("--test", required=True, help="the held-out test")
    s.add_argument("--title", default=None, help="figure title")
    s.add_argument("--out", required=True, help="PNG file")
    s.set_defaults(func=_plot_fold)


def _add_track(sub) -> None:
    s = sub.add_parser("track", help="log an evaluation to MLflow (idempotent: runs keyed by tags)")
    s.add_argument("results", help="results folder holding iso_table.csv and the fold JSON files")
    s.add_argument("--tracking-uri", default=None, help="MLflow tracking URI (default: MLFLOW_TRACKING_URI, "
                   "else sqlite:///mlflow.db in the working folder)")
    s.add_argument("--config-json", default=None, help="the workflow config as JSON (hashed into a tag)")
    s.add_argument("--folds", nargs="+", default=None, metavar="FOLD_JSON",
                   help="the fold JSON files to log (default: every *.fold.json below the results folder)")
    s.add_argument("--out", default=None, help="write the logged run ids as JSON here")
    s.set_defaults(func=_track)


def _add_register(sub) -> None:
    s = sub.add_parser("register", help="log a final model to MLflow as a pyfunc model and register it "
                       "(mlflow models serve answers with pulses)")
    s.add_argument("model", help="model file (.cfmodel) fitted on every test")
    s.add_argument("--surrogate", required=True, help="the CAE surrogate file the model refers to")
    s.add_argument("--campaign-name", required=True, help="names the experiment and the registered model")
    s.add_argument("--inputs", required=True, help="the model's input mode (paper, state or auto)")
    s.add_argument("--label", required=True, help="the model's label (K1, K2 ... or auto)")
    s.add_argument("--conditions-json", required=True,
                   help="conditions as a JSON list of objects (v0_mph, front_weight_lb, rear_weight_lb, "
                        "powertrain, drive, name): the input example")
    s.add_argument("--artifacts", nargs="*", default=[], help="further files of the run (predictions, figures)")
    s.add_argument("--tracking-uri", default=None, help="MLflow tracking URI (default: MLFLOW_TRACKING_URI, "
                   "else sqlite:///mlflow.db in the working folder)")
    s.add_argument("--samples", type=_positive, default=1000, help="the served model's Monte Carlo samples")
    s.add_argument("--seed", type=_seed, default=0, help="the served model's seed (default 0)")
    s.add_argument("--out", default=None, help="write name, version, run id and model URI as JSON here")
    s.set_defaults(func=_register)


# The flag of each setting that a command's InputError may name: the library names the setting
# (its parameter or MethodConfig field), the command line the flag it came from.
_METHOD_FLAGS = {"k": "--k", "inputs": "--inputs", "holdout": "--holdout", "random_state": "--seed",
                 "assignment": "--assignment", "use_companion": "--use-companion", "extra_inputs": "--extra-inputs",
                 "cae_decel": "--cae-decel", "n_grid": "--n-grid", "trend": "--trend", "pooled": "--pooled",
                 "onset": "--onset", "shrink": "--shrink", "chain": "--chain", "effects": "--effects"}
_FLAGS = {
    "fit": _METHOD_FLAGS,
    "rollout": {"n_samples": "--samples", "band": "--band", "test": "--test"},
    "score": {"test": "--test", "windows": "--windows"},
    "plot fold": {"test": "--test"},
    "evaluate": {**_METHOD_FLAGS, "n_samples": "--samples", "band": "--band", "out": "--out", "auto": "--auto",
                 "windows": "--windows"},
    "predict": {"n_samples": "--samples", "random_state": "--seed", "band": "--band"},
    "diagnose": {"effects": "--effects", "threshold": "--threshold", "alpha": "--alpha", "move": "--move",
                 "k": "--k", "inputs": "--inputs", "n_samples": "--samples", "random_state": "--seed",
                 "fold_models": "--fold-models"},
    "report": {"score": "--score"},
    "plot summary": {"score": "--score", "window": "--window"},
    "world generate": {"preset": "--preset", "withhold": "--withhold", "strength": "--strength",
                       "overrides": "--effect-param", "seed": "--seed", "matrix": "--matrix", "n_cae": "--n-cae",
                       "n_tests": "--n-tests"},
    "world calibrate": {"max_nfev": "--max-evals"},
    "world noise-control": {"noise_g": "--noise-g"},
    "world validate": {"withhold": "--effects", "strength": "--strengths", "seed": "--seeds", "worlds": "--worlds"},
    "world validate-method": {"worlds": "--worlds", "withheld": "--withheld", "strengths": "--strengths",
                              "seeds": "--seeds", "matrices": "--matrices", "n_cae": "--n-cae",
                              "inputs": "--inputs", "ks": "--k", "n_samples": "--samples", "out": "--out",
                              "work": "--work", "effects": "--effects", "windows": "--windows"},
}


def _named_by_flag(err: InputError, args) -> InputError:
    """``err`` with its field renamed to the flag it came from, for the command in ``args``."""
    command = " ".join(filter(None, (getattr(args, name, None)
                                     for name in ("command", "world_command", "plot_command"))))
    flag = _FLAGS.get(command, {}).get(err.field)
    return err if flag is None else InputError(err.message, err.file, flag)


def main(argv: list[str] | None = None) -> int:
    if argv is None and forkserver.wanted(sys.argv[1:]):
        code = forkserver.forward(os.environ[forkserver.ADDRESS], sys.argv[1:])
        if code is not None:
            return code
    args = None
    try:
        args = _build_parser().parse_args(argv)
        return args.func(args)
    except InputError as err:
        print(f"crashfuse: error: {_named_by_flag(err, args)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except Exception as err:  # noqa: BLE001 - the documented exit code 1
        if os.environ.get("CRASHFUSE_DEBUG"):
            raise
        print(f"crashfuse: internal error: {type(err).__name__}: {err} (set CRASHFUSE_DEBUG=1 for a traceback)",
              file=sys.stderr)
        return 1
