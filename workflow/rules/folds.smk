# One leave-one-test-out fold (input mode x K x held-out test) as the method's steps, each a job:
# train (the bias models fitted without the test) -> rollout (its condition predicted, with the band)
# -> score (ISO rows, band coverage, fold JSON) and figure. A change of the ISO windows reruns only
# score; of the Monte Carlo samples, rollout and after; of a method setting, train and after. The
# jobs of one fold share a group, so a cluster executor can run a fold's chain as one job.


wildcard_constraints:
    inputs="paper|state",
    k=r"[1-9][0-9]*",
    test=r"[^/]+",


rule train:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
    output:
        fold_path("model.cfmodel"),
    params:
        method=method_args(),
    group:
        "fold"
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/K{{k}}/{{test}}/train.log",
    benchmark:
        f"{RESULTS}/benchmarks/folds/{{inputs}}/K{{k}}/{{test}}/train.tsv"
    shell:
        "crashfuse fit {input.campaign:q} --k {wildcards.k} --inputs {wildcards.inputs}"
        " --holdout {wildcards.test:q} --surrogate {input.surrogate:q} {params.method} --out {output:q}"
        " > {log:q} 2>&1"


rule rollout:
    input:
        campaign=campaign_dir,
        model=fold_path("model.cfmodel"),
    output:
        prediction=fold_path("{test}_prediction.csv"),
        facts=fold_path("{test}.rollout.json"),
    params:
        samples=METHOD["samples"],
        out=lambda wildcards, output: Path(output.facts).parent,
    group:
        "fold"
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/K{{k}}/{{test}}/rollout.log",
    benchmark:
        f"{RESULTS}/benchmarks/folds/{{inputs}}/K{{k}}/{{test}}/rollout.tsv"
    shell:
        "crashfuse rollout {input.model:q} {input.campaign:q} --test {wildcards.test:q}"
        " --samples {params.samples} --out {params.out:q} > {log:q} 2>&1"


rule score:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
        prediction=fold_path("{test}_prediction.csv"),
        facts=fold_path("{test}.rollout.json"),
    output:
        table=fold_path("iso_table.csv"),
        coverage=fold_path("coverage.csv"),
        json=fold_path("{test}.fold.json"),
    params:
        windows=" ".join(config["scoring"]["windows"]),
        out=lambda wildcards, output: Path(output.json).parent,
    group:
        "fold"
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/K{{k}}/{{test}}/score.log",
    shell:
        "crashfuse score {input.campaign:q} {params.out:q} --test {wildcards.test:q} --windows {params.windows}"
        " --surrogate {input.surrogate:q} --table-dir {params.out:q} > {log:q} 2>&1"


rule figure:
    input:
        campaign=campaign_dir,
        prediction=fold_path("{test}_prediction.csv"),
    output:
        report(
            fold_path("{test}.png"),
            category="Folds",
            subcategory="{inputs} inputs",
            labels={"test": "{test}", "K": "{k}"},
        ),
    params:
        title="{test}: {inputs} inputs, K = {k}",
    group:
        "fold"
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/K{{k}}/{{test}}/figure.log",
    shell:
        "crashfuse plot fold {input.campaign:q} {input.prediction:q} --test {wildcards.test:q}"
        " --title {params.title:q} --out {output:q} > {log:q} 2>&1"
