# The engineer's deliverable: models fitted on every test, and their predictions at conditions
# nobody tested (config `predictions`): prediction CSV (CAE, corrected mean, 95 % band), the pulse
# metrics with their band and extrapolation flags (JSON), and a figure that says when it is outside.


rule final_model:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
        pooled=pooled_final_model,
    output:
        final_path(),
    wildcard_constraints:
        inputs="paper|state",
        model=r"K[1-9][0-9]*",
    params:
        k=lambda wildcards: wildcards.model[1:],
        method=method_args(),
        pooled=pooled_flag,
    log:
        f"{RESULTS}/logs/final/{{inputs}}/{{model}}.log",
    benchmark:
        f"{RESULTS}/benchmarks/final/{{inputs}}/{{model}}.tsv"
    shell:
        "crashfuse fit {input.campaign:q} --k {params.k} --inputs {wildcards.inputs} --surrogate {input.surrogate:q}"
        " {params.method} {params.pooled} --out {output:q} > {log:q} 2>&1"


rule final_auto:
    input:
        campaign=campaign_dir,
        surrogate=f"{RESULTS}/surrogate.cfmodel",
        models=[final_path(i, f"K{k}") for i in AUTO_INPUTS for k in config["ks"]],
    output:
        final_path("auto", "auto"),
    log:
        f"{RESULTS}/logs/final/auto.log",
    shell:
        "crashfuse select {input.campaign:q} {input.models:q} --out {output:q} > {log:q} 2>&1"


rule predict:
    input:
        model=final_path(),
        surrogate=f"{RESULTS}/surrogate.cfmodel",
    output:
        csv=f"{RESULTS}/predictions/{{inputs}}/{{model}}/{{condition}}.csv",
        json=f"{RESULTS}/predictions/{{inputs}}/{{model}}/{{condition}}.json",
    params:
        condition=condition_args,
        samples=METHOD["samples"],
        seed=METHOD["seed"],
    log:
        f"{RESULTS}/logs/predictions/{{inputs}}/{{model}}/{{condition}}.log",
    shell:
        "crashfuse predict {input.model:q} --surrogate {input.surrogate:q} {params.condition} --samples {params.samples}"
        " --seed {params.seed}"
        " --out {output.csv:q} --json > {output.json:q} 2> {log:q}"


rule prediction_figure:
    input:
        csv=f"{RESULTS}/predictions/{{inputs}}/{{model}}/{{condition}}.csv",
        json=f"{RESULTS}/predictions/{{inputs}}/{{model}}/{{condition}}.json",
    output:
        report(
            f"{RESULTS}/predictions/{{inputs}}/{{model}}/{{condition}}.png",
            category="Predictions",
            labels={"condition": "{condition}", "model": "{inputs} {model}"},
        ),
    params:
        title=lambda wildcards: f"{wildcards.condition}: {prediction_label(wildcards)}",
    log:
        f"{RESULTS}/logs/predictions/{{inputs}}/{{model}}/{{condition}}.figure.log",
    shell:
        "crashfuse plot prediction {input.csv:q} --json {input.json:q} --title {params.title:q} --out {output:q}"
        " > {log:q} 2>&1"
