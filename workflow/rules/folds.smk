# One leave-one-test-out fold (input mode x K x held-out test) as the method's steps, each a job:
# train (the bias models fitted without the test; its model file refers to the shared surrogate file) -> rollout (its condition predicted, with the band)
# -> score (ISO rows, band coverage, fold JSON) and figure. A change of the ISO windows reruns only
# score; of the Monte Carlo samples, rollout and after; of a method setting, train and after. A
# larger K's train reuses the pooled GP in the smallest K's model of the same test (the same fit).
# The jobs of one fold share a group, so a cluster executor can run a fold's chain as one job (one
# group per fold: under one name for all, the pooled-GP edge would merge a test's folds). With
# `auto`, each test's `auto` job picks among its candidates' rollouts (inner error), and that
# fold (inputs and model `auto`) is scored and drawn by the same rules.

FOLD_GROUP = "fold-{inputs}-{model}-{test}"


wildcard_constraints:
    inputs="paper|state|auto",
    model=r"K[1-9][0-9]*|auto",
    test=r"[^/]+",


rule train:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
        pooled=pooled_model,
    output:
        fold_path("model.cfmodel"),
    wildcard_constraints:
        inputs="paper|state",
        model=r"K[1-9][0-9]*",
    params:
        k=lambda wildcards: wildcards.model[1:],
        method=method_args(),
        pooled=pooled_flag,
    group:
        FOLD_GROUP
    priority: train_priority
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/{{model}}/{{test}}/train.log",
    benchmark:
        f"{RESULTS}/benchmarks/folds/{{inputs}}/{{model}}/{{test}}/train.tsv"
    shell:
        "crashfuse fit {input.campaign:q} --k {params.k} --inputs {wildcards.inputs}"
        " --holdout {wildcards.test:q} --surrogate {input.surrogate:q} {params.method} {params.pooled}"
        " --out {output:q}"
        " > {log:q} 2>&1"


rule rollout:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
        model=fold_path("model.cfmodel"),
    output:
        prediction=fold_path("{test}_prediction.csv"),
        facts=fold_path("{test}.rollout.json"),
    wildcard_constraints:
        inputs="paper|state",
        model=r"K[1-9][0-9]*",
    params:
        samples=METHOD["samples"],
        inner=lambda wildcards: "--inner" if config["auto"] and wildcards.inputs in AUTO_INPUTS else "",
        out=lambda wildcards, output: Path(output.facts).parent,
    group:
        FOLD_GROUP
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/{{model}}/{{test}}/rollout.log",
    benchmark:
        f"{RESULTS}/benchmarks/folds/{{inputs}}/{{model}}/{{test}}/rollout.tsv"
    shell:
        "crashfuse rollout {input.model:q} {input.campaign:q} --test {wildcards.test:q} --surrogate {input.surrogate:q}"
        " --samples {params.samples} {params.inner} --out {params.out:q} > {log:q} 2>&1"


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
        FOLD_GROUP
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/{{model}}/{{test}}/score.log",
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
            labels={"test": "{test}", "model": "{model}"},
        ),
    params:
        title=fold_title,
    group:
        FOLD_GROUP
    log:
        f"{RESULTS}/logs/folds/{{inputs}}/{{model}}/{{test}}/figure.log",
    shell:
        "crashfuse plot fold {input.campaign:q} {input.prediction:q} --test {wildcards.test:q}"
        " --title {params.title:q} --out {output:q} > {log:q} 2>&1"


rule auto:
    input:
        lambda wildcards: candidate_files("{test}.rollout.json", wildcards.test),
    output:
        prediction=f"{RESULTS}/folds/auto/auto/{{test}}/{{test}}_prediction.csv",
        facts=f"{RESULTS}/folds/auto/auto/{{test}}/{{test}}.rollout.json",
    params:
        inputs=" ".join(AUTO_INPUTS),
        out=lambda wildcards, output: Path(output.facts).parent,
    log:
        f"{RESULTS}/logs/folds/auto/auto/{{test}}/auto.log",
    shell:
        "crashfuse auto {input:q} --inputs {params.inputs} --out {params.out:q} > {log:q} 2>&1"
