# The sim-to-real gap diagnosis of the campaign (`crashfuse diagnose`) and, on request, the
# withheld-effect validation matrix (`crashfuse world validate`, the one reader of world.json).

DIAG = config["diagnosis"]


rule diagnose:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
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
    log:
        f"{RESULTS}/logs/diagnose.log",
    benchmark:
        f"{RESULTS}/benchmarks/diagnose.tsv"
    shell:
        "crashfuse diagnose {input.campaign:q} --surrogate {input.surrogate:q} --effects {params.effects} "
        "{params.flags} --out {params.out:q} > {log:q} 2>&1"


rule validate_diagnosis:
    output:
        table=f"{RESULTS}/diagnosis/validation.csv",
        markdown=report(f"{RESULTS}/diagnosis/validation.md", category="Diagnosis"),
    params:
        out=lambda wildcards, output: Path(output.table).parent,
        strengths=" ".join(config["validation"]["strengths"]),
        seeds=" ".join(str(s) for s in config["validation"]["seeds"]),
    log:
        f"{RESULTS}/logs/validate_diagnosis.log",
    shell:
        "crashfuse world validate --strengths {params.strengths} --seeds {params.seeds} "
        "--out {params.out:q} > {log:q} 2>&1"
