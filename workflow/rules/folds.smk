# One job per fold (input mode x K x held-out test): fit the bias models without the test, roll
# out its condition, score it against the test (CAE and corrected rows) and draw its figure.
# Snakemake runs the folds in parallel, so each evaluate runs in one process (--jobs 1).


wildcard_constraints:
    inputs="paper|state",
    k=r"[1-9][0-9]*",
    test=r"[^/]+",


rule fold:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
    output:
        table=fold_dir("iso_table.csv"),
        coverage=fold_dir("coverage.csv"),
        prediction=fold_path("{test}_prediction.csv"),
        json=fold_path("{test}.fold.json"),
        figure=report(
            fold_path("{test}.png"),
            category="Folds",
            subcategory="{inputs} inputs",
            labels={"test": "{test}", "K": "{k}"},
        ),
    params:
        method=method_args(),
        out=lambda wildcards, output: Path(output.table).parent,
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/K{{k}}/{{test}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/folds/{{inputs}}/K{{k}}/{{test}}.tsv"
    shell:
        "crashfuse evaluate {input.campaign:q} --k {wildcards.k} --inputs {wildcards.inputs}"
        " --holdout {wildcards.test:q} --surrogate {input.surrogate:q} {params.method} --jobs 1"
        " --out {params.out:q}"
        " > {log:q} 2>&1"
