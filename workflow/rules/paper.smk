# The published experiments of 004 under the published conditions (issue 16): not part
# of `all`; run with `snakemake paper` (`make paper`). The held-out tables of 004 ch. 16
# use the first capture of the config (the demo by default), built up to its
# observation map if needed; their fits run in a temporary folder.
from pathlib import Path

PAPER_SID = next(iter(CAPTURES))


rule paper:
    input:
        capture=CAPTURES[PAPER_SID],
        poses=f"{PROC}/{PAPER_SID}/camera/poses.yaml",
        obs=f"{PROC}/{PAPER_SID}/observation.zarr",
    output:
        directory(f"{REPORTS}/paper"),
    params:
        cli=PARAMMAP,
        processed=lambda wc, input: str(Path(input.obs).parent),
    threads: WORKERS or workflow.cores
    log:
        "logs/paper.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} paper --out {output} --capture {input.capture}"
        " --processed {params.processed} --workers {threads} 2> {log}"
