# Observation map: one job per surface writes observation.zarr (never two jobs on one
# store), streaming over views.


rule observation:
    input:
        capture=capture_dir,
        poses=f"{PROC}/{{sid}}/camera/poses.yaml",
        intrinsics=f"{PROC}/{{sid}}/camera/intrinsics.yaml",
        radiometry=f"{PROC}/{{sid}}/camera/radiometry.json",
    output:
        store=directory(f"{PROC}/{{sid}}/observation.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/observation.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("observation"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    threads: WORKERS
    log:
        "logs/observation/{sid}.log",
    benchmark:
        "logs/benchmarks/{sid}/observation.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} observe {input.capture} --out {params.out} {params.cfg}"
        " --workers {threads} 2> {log}"
