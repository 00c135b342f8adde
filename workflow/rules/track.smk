# MLflow: one serial logging step after every fold (SQLite takes one writer at a time; see
# crashfuse/tracking.py). Runs are keyed by tags, so a rerun updates its runs instead of adding more.
# The fold JSON files are passed explicitly: folds of an earlier, wider config may still lie in results/.


rule track:
    input:
        table=f"{RESULTS}/iso_table.csv",
        folds=lambda wildcards: fold_files(fold_path("{test}.fold.json")),
        figures=lambda wildcards: fold_files(fold_path("{test}.png")),
    output:
        f"{RESULTS}/tracking.json",
    params:
        uri=(
            f"--tracking-uri {shlex.quote(config['tracking']['uri'])}"
            if config["tracking"]["uri"]
            else ""
        ),
        config=json.dumps(config, sort_keys=True),
        results=lambda wildcards, input: Path(input.table).parent,
    log:
        f"{RESULTS}/logs/track.log",
    shell:
        "crashfuse track {params.results:q} --folds {input.folds:q} {params.uri} --config-json {params.config:q} "
        "--out {output:q} > {log:q} 2>&1"
