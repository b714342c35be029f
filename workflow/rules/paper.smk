# The published experiments of 004 under the published conditions (issue 16): not part
# of `all`; run with `snakemake paper` (`make paper`).


rule paper:
    output:
        directory(f"{REPORTS}/paper"),
    params:
        cli=PARAMMAP,
    log:
        "logs/paper.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} paper --out {output} 2> {log}"
