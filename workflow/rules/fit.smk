# Model fits: one job per model writes fit/<model>.zarr (dask over texel tiles inside
# the job; scheduler from config.fit.scheduler), its metrics and figures.


rule fit_mh:
    input:
        capture=capture_dir,
        obs=f"{PROC}/{{sid}}/observation.zarr",
    output:
        store=directory(f"{PROC}/{{sid}}/fit/mh-{{K}}.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/fit-mh-{{K}}.json",
        params=report(
            f"{REPORTS}/{{sid}}/mh-{{K}}_params.png",
            caption="../report/mh_params.rst",
            category="MH model",
            subcategory="{sid}",
        ),
        residuals=report(
            f"{REPORTS}/{{sid}}/mh-{{K}}_residuals.png",
            caption="../report/mh_residuals.rst",
            category="MH model",
            subcategory="{sid}",
        ),
        lobes=report(
            f"{REPORTS}/{{sid}}/mh-{{K}}_lobes.png",
            caption="../report/mh_lobes.rst",
            category="MH model",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("fit", "observation"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    wildcard_constraints:
        K="[0-9]+|auto",
    threads: WORKERS
    log:
        "logs/fit/{sid}/mh-{K}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} fit-mh {input.capture} --out {params.out} --lobes {wildcards.K}"
        " {params.cfg} --figures {params.figures} --workers {threads} 2> {log}"


rule fit_sh:
    input:
        capture=capture_dir,
        obs=f"{PROC}/{{sid}}/observation.zarr",
    output:
        store=directory(f"{PROC}/{{sid}}/fit/sh-{{hemi}}-{{nc}}.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/fit-sh-{{hemi}}-{{nc}}.json",
        params=report(
            f"{REPORTS}/{{sid}}/sh-{{hemi}}-{{nc}}_params.png",
            caption="../report/sh_params.rst",
            category="SH model",
            subcategory="{sid}",
        ),
        residuals=report(
            f"{REPORTS}/{{sid}}/sh-{{hemi}}-{{nc}}_residuals.png",
            caption="../report/sh_residuals.rst",
            category="SH model",
            subcategory="{sid}",
        ),
        lobes=report(
            f"{REPORTS}/{{sid}}/sh-{{hemi}}-{{nc}}_lobes.png",
            caption="../report/sh_lobes.rst",
            category="SH model",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("fit", "observation"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    wildcard_constraints:
        hemi="zh|mirror|lsop|rlsop|wls",
        nc="[0-9]+",
    threads: WORKERS
    log:
        "logs/fit/{sid}/sh-{hemi}-{nc}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} fit-sh {input.capture} --out {params.out}"
        " --model sh-{wildcards.hemi}-{wildcards.nc} {params.cfg}"
        " --figures {params.figures} --workers {threads} 2> {log}"
