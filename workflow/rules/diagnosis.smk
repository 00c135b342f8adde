# The sim-to-real gap diagnosis of the campaign (`crashfuse diagnose`) and, on request, the
# withheld-effect validation matrix (`crashfuse world validate`, the one reader of world.json)
# and the method validation matrix (`crashfuse world validate-method`).


rule diagnose:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
        fold_models=diagnosis_fold_models,
    output:
        json=f"{RESULTS}/diagnosis/diagnosis.json",
        markdown=report(f"{RESULTS}/diagnosis/diagnosis.md", category="Diagnosis"),
        shrink=f"{RESULTS}/diagnosis/shrink.csv",
    params:
        out=lambda wildcards, output: Path(output.json).parent,
        effects=" ".join(DIAG["effects"]),
        flags=(
            f"--threshold {DIAG['threshold']} --k {DIAG['k']} --samples {DIAG['samples']} "
            f"--seed {METHOD['seed']}" + ("" if DIAG["residual"] else " --no-residual")
        ),
        fold_models=fold_models_flag,
    log:
        f"{RESULTS}/logs/diagnose.log",
    benchmark:
        f"{RESULTS}/benchmarks/diagnose.tsv"
    threads: 1  # beside the folds; --set-threads diagnose=2 on a machine of its own
    priority: 1  # as soon as its inputs exist: the longest job, run alone at the end it would idle a core
    shell:
        "crashfuse diagnose {input.campaign:q} --surrogate {input.surrogate:q} --effects {params.effects} --jobs {threads} "
        "{params.flags} {params.fold_models} --out {params.out:q} > {log:q} 2>&1"


rule validate_diagnosis:
    output:
        table=f"{RESULTS}/diagnosis/validation.csv",
        markdown=report(f"{RESULTS}/diagnosis/validation.md", category="Diagnosis"),
    params:
        out=lambda wildcards, output: Path(output.table).parent,
        strengths=" ".join(config["validation"]["strengths"]),
        seeds=" ".join(str(s) for s in config["validation"]["seeds"]),
        worlds=" ".join(config["validation"]["worlds"]),
        pairs="--pairs" if config["validation"]["pairs"] else "",
        n_cae=config["validation"]["n_cae"],
    log:
        f"{RESULTS}/logs/validate_diagnosis.log",
    threads: 2  # campaigns at once (scaled down to the cores given)
    shell:
        "crashfuse world validate --worlds {params.worlds} --strengths {params.strengths} --seeds {params.seeds} "
        "{params.pairs} --n-cae {params.n_cae} --jobs {threads} --out {params.out:q} > {log:q} 2>&1"


MATRIX = config["validation"]["method"]


rule validate_method:
    output:
        table=f"{RESULTS}/validation/method_matrix.csv",
        summary=f"{RESULTS}/validation/method_summary.csv",
        markdown=report(f"{RESULTS}/validation/method_matrix.md", category="Validation"),
    params:
        out=lambda wildcards, output: Path(output.table).parent,
        spread=(
            f"--worlds {' '.join(MATRIX['worlds'])} --withheld {' '.join(MATRIX['withheld'])} "
            f"--strengths {' '.join(MATRIX['strengths'])} --seeds {' '.join(map(str, MATRIX['seeds']))} "
            f"--matrices {' '.join(MATRIX['matrices'])} --n-cae {' '.join(map(str, MATRIX['n_cae']))} "
            f"--inputs {' '.join(MATRIX['inputs'])} --k {' '.join(map(str, MATRIX['ks']))} "
            f"{'--auto ' if MATRIX['auto'] else ''}--effects {' '.join(MATRIX['effects'])} "
            f"--windows {' '.join(MATRIX['windows'])} "
            f"--samples {MATRIX['samples']} --seed {MATRIX['seed']}"
        ),
    threads: 2
    log:
        f"{RESULTS}/logs/validate_method.log",
    shell:
        "crashfuse world validate-method {params.spread} --jobs {threads} --out {params.out:q} > {log:q} 2>&1"
