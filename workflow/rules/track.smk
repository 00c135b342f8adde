# MLflow: one serial logging step after every fold (SQLite takes one writer at a time; see
# crashfuse/tracking.py). Runs are keyed by tags, so a rerun updates its runs instead of adding more.
# The fold JSON files are passed explicitly: folds of an earlier, wider config may still lie in results/.

TRACKING_URI_ARG = f"--tracking-uri {shlex.quote(config['tracking']['uri'])}" if config["tracking"]["uri"] else ""


rule track:
    input:
        table=f"{RESULTS}/iso_table.csv",
        folds=lambda wildcards: fold_files(fold_path("{test}.fold.json")),
        figures=lambda wildcards: fold_files(fold_path("{test}.png")),
    output:
        f"{RESULTS}/tracking.json",
    params:
        uri=TRACKING_URI_ARG,
        config=json.dumps(config, sort_keys=True),
        results=lambda wildcards, input: Path(input.table).parent,
    log:
        f"{RESULTS}/logs/track.log",
    shell:
        "crashfuse track {params.results:q} --folds {input.folds:q} {params.uri} --config-json {params.config:q} "
        "--out {output:q} > {log:q} 2>&1"


# Each final model of `predictions` as an MLflow pyfunc model, registered per campaign
# (`crashfuse-<campaign>` for auto): `mlflow models serve -m models:/<name>/<version>` answers with pulses.
rule register:
    input:
        model=final_path(),
        surrogate=f"{RESULTS}/surrogate.cfmodel",
        predictions=lambda wildcards: [
            f for suffix in (".csv", ".json", ".png")
            for f in prediction_files(suffix, [(wildcards.inputs, wildcards.model)])
        ],
        after=registration_inputs,
    output:
        f"{RESULTS}/registered/{{inputs}}/{{model}}.json",
    params:
        uri=TRACKING_URI_ARG,
        campaign=lambda wildcards: Path(campaign_dir()).name,
        conditions=json.dumps(PREDICT["conditions"]),
        samples=METHOD["samples"],
        seed=METHOD["seed"],
    log:
        f"{RESULTS}/logs/registered/{{inputs}}/{{model}}.log",
    shell:
        "crashfuse register {input.model:q} --surrogate {input.surrogate:q} --campaign-name {params.campaign:q}"
        " --inputs {wildcards.inputs} --label {wildcards.model} --conditions-json {params.conditions:q}"
        " --artifacts {input.predictions:q} {params.uri} --samples {params.samples} --seed {params.seed}"
        " --out {output:q} > {log:q} 2>&1"
