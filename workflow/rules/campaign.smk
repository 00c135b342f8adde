# The campaign (the world's paper preset generated into <results>/paper unless config names a
# folder) and the CAE surrogate, fitted once on its CAE runs and shared by every fold.


checkpoint campaign:
    output:
        folder=directory(CAMPAIGN),
    params:
        seed=config["campaign"]["seed"],
        n_cae=(
            f"--n-cae {config['campaign']['n_cae']}"
            if config["campaign"]["n_cae"] is not None
            else ""
        ),
    log:
        f"{RESULTS}/logs/campaign.log",
    shell:
        "crashfuse world generate --out {output.folder:q} --seed {params.seed} {params.n_cae} > {log:q} 2>&1"


rule prepare:
    input:
        campaign=campaign_dir,
    output:
        f"{RESULTS}/surrogate.cfmodel",
    params:
        seed=METHOD["seed"],
    log:
        f"{RESULTS}/logs/prepare.log",
    benchmark:
        f"{RESULTS}/benchmarks/prepare.tsv"
    shell:
        "crashfuse prepare {input.campaign:q} --seed {params.seed} --out {output:q} > {log:q} 2>&1"
