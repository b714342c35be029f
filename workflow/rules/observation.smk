# Observation map: one job per surface writes observation.zarr (never two jobs on one
# store), streaming over views; figures come from the store.


rule observation:
    input:
        capture=capture_dir,
        poses=f"{PROC}/{{sid}}/camera/poses.yaml",
        intrinsics=f"{PROC}/{{sid}}/camera/intrinsics.yaml",
    output:
        store=directory(f"{PROC}/{{sid}}/observation.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/observation.json",
        counts=report(
            f"{REPORTS}/{{sid}}/observation_valid_count.png",
            caption="../report/observation_valid_count.rst",
            category="Observation map",
            subcategory="{sid}",
        ),
        lobes=report(
            f"{REPORTS}/{{sid}}/observation_lobes.png",
            caption="../report/observation_lobes.rst",
            category="Observation map",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("observation"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    threads: WORKERS
    log:
        "logs/observation/{sid}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} observe {input.capture} --out {params.out} {params.cfg}"
        " --figures {params.figures} --workers {threads} 2> {log}"
