# After all folds: the ISO table (one file), the paper's Table 2 as Markdown and LaTeX with the
# summary, and the summary figure of ISO score by test and K.


rule aggregate:
    input:
        tables=lambda wildcards: fold_files(fold_path("iso_table.csv")),
    output:
        report(f"{RESULTS}/iso_table.csv", category="Table"),
    log:
        f"{RESULTS}/logs/aggregate.log",
    shell:
        "crashfuse aggregate {input.tables:q} --out {output:q} > {log:q} 2>&1"


rule tables:
    input:
        f"{RESULTS}/iso_table.csv",
    output:
        markdown=report(
            expand(f"{RESULTS}/tables/table2_{{inputs}}.md", inputs=table_inputs()),
            category="Table",
        ),
        latex=expand(f"{RESULTS}/tables/table2_{{inputs}}.tex", inputs=table_inputs()),
        summary=report(f"{RESULTS}/tables/summary.md", category="Table"),
        summary_csv=f"{RESULTS}/tables/summary.csv",
    params:
        out=lambda wildcards, output: Path(output.summary).parent,
    log:
        f"{RESULTS}/logs/tables.log",
    shell:
        "crashfuse report {input:q} --out {params.out:q} > {log:q} 2>&1"


rule summary_figure:
    input:
        f"{RESULTS}/iso_table.csv",
    output:
        report(f"{RESULTS}/figures/iso_summary.png", category="Summary"),
    params:
        window="0-60",
    log:
        f"{RESULTS}/logs/summary_figure.log",
    shell:
        "crashfuse plot summary {input:q} --window {params.window} --out {output:q} > {log:q} 2>&1"
