# Model fits: one job per model writes fit/<model>.zarr (dask over texel tiles inside
# the job; scheduler from config.fit.scheduler) and its metrics; then the parameter-map
# EXR. Model names follow outputs.md: mh-<K> and sh-<hemisphere>-<coefficients>; the
# SH baked from an MH fit is sh-mh-<coefficients>; the
# basis materials (003) are the MH map mh-materials, refitted from another MH fit;
# svbrdf-ggx is fitted under the lights the lights rule found (report.smk).


rule fit_mh:
    input:
        obs=f"{PROC}/{{sid}}/observation.zarr",
    output:
        store=directory(f"{PROC}/{{sid}}/fit/mh-{{K}}.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/fit-mh-{{K}}.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("fit"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    wildcard_constraints:
        K="[0-9]+|auto",
    threads: WORKERS
    log:
        "logs/fit/{sid}/mh-{K}.log",
    benchmark:
        "logs/benchmarks/{sid}/fit-mh-{K}.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} fit-mh --out {params.out} --lobes {wildcards.K}"
        " {params.cfg} --workers {threads} 2> {log}"


rule fit_sh:
    input:
        obs=f"{PROC}/{{sid}}/observation.zarr",
    output:
        store=directory(f"{PROC}/{{sid}}/fit/sh-{{hemi}}-{{nc}}.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/fit-sh-{{hemi}}-{{nc}}.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("fit"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    wildcard_constraints:
        hemi="zh|mirror|lsop|rlsop|wls",
        nc="[0-9]+",
    threads: WORKERS
    log:
        "logs/fit/{sid}/sh-{hemi}-{nc}.log",
    benchmark:
        "logs/benchmarks/{sid}/fit-sh-{hemi}-{nc}.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} fit-sh --out {params.out}"
        " --model sh-{wildcards.hemi}-{wildcards.nc} {params.cfg} --workers {threads} 2> {log}"


rule bake_sh:
    input:
        obs=f"{PROC}/{{sid}}/observation.zarr",
        source=lambda wc: f"{PROC}/{wc.sid}/fit/{sh_source()}.zarr",
    output:
        store=directory(f"{PROC}/{{sid}}/fit/sh-mh-{{nc}}.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/fit-sh-mh-{{nc}}.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("fit"),
        source=lambda wc: sh_source(),
        out=lambda wc: f"{PROC}/{wc.sid}",
    wildcard_constraints:
        nc="[0-9]+",
    threads: WORKERS
    log:
        "logs/fit/{sid}/sh-mh-{nc}.log",
    benchmark:
        "logs/benchmarks/{sid}/fit-sh-mh-{nc}.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} fit-sh --out {params.out} --model sh-mh-{wildcards.nc} {params.cfg}"
        " --set fit.sh.source={params.source} --workers {threads} 2> {log}"


rule fit_svbrdf:
    input:
        obs=f"{PROC}/{{sid}}/observation.zarr",
        lights=f"{PROC}/{{sid}}/camera/lights.yaml",
    output:
        store=directory(f"{PROC}/{{sid}}/fit/svbrdf-ggx.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/fit-svbrdf-ggx.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("fit"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    threads: WORKERS
    log:
        "logs/fit/{sid}/svbrdf-ggx.log",
    benchmark:
        "logs/benchmarks/{sid}/fit-svbrdf-ggx.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} fit-svbrdf --out {params.out} {params.cfg} --workers {threads} 2> {log}"


rule materials:
    input:
        obs=f"{PROC}/{{sid}}/observation.zarr",
        source=lambda wc: f"{PROC}/{wc.sid}/fit/{mh_source('materials')}.zarr",
    output:
        store=directory(f"{PROC}/{{sid}}/fit/mh-materials.zarr"),
        metrics=f"{PROC}/{{sid}}/metrics/fit-mh-materials.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("materials"),
        source=lambda wc: mh_source("materials"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    threads: WORKERS
    log:
        "logs/fit/{sid}/mh-materials.log",
    benchmark:
        "logs/benchmarks/{sid}/fit-mh-materials.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} materials --out {params.out} {params.cfg}"
        " --set materials.source={params.source} --workers {threads} 2> {log}"


rule export_params:
    input:
        fit=f"{PROC}/{{sid}}/fit/{{model}}.zarr",
    output:
        f"{PROC}/{{sid}}/params/{{model}}.exr",
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
    wildcard_constraints:
        model="(mh|sh|svbrdf)-[a-z0-9-]+",
    log:
        "logs/export/{sid}/{model}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} export --out {params.out} --model {wildcards.model}"
        " 2> {log}"


rule material:
    input:
        exr=f"{PROC}/{{sid}}/params/svbrdf-ggx.exr",
    output:
        gltf=f"{PROC}/{{sid}}/params/svbrdf-ggx.gltf",
        mtlx=f"{PROC}/{{sid}}/params/svbrdf-ggx.mtlx",
        metrics=f"{PROC}/{{sid}}/metrics/material-svbrdf-ggx.json",
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
    log:
        "logs/export/{sid}/material.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} material --out {params.out} --model svbrdf-ggx 2> {log}"


rule export_diffuse:
    input:
        obs=f"{PROC}/{{sid}}/observation.zarr",
    output:
        f"{PROC}/{{sid}}/params/diffuse.exr",
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
    log:
        "logs/export/{sid}/diffuse.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} export --out {params.out} --model diffuse 2> {log}"


rule best:
    input:
        obs=f"{PROC}/{{sid}}/observation.zarr",
        params=lambda wc: expand(f"{PROC}/{wc.sid}/params/{{m}}.exr", m=models() + ["diffuse"]),
    output:
        params=f"{PROC}/{{sid}}/params/best.exr",
        metrics=f"{PROC}/{{sid}}/metrics/best.json",
        figure=report(
            f"{REPORTS}/{{sid}}/best_choice.png",
            caption="../report/best_choice.rst",
            category="3 Models",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("best"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
        models=" ".join(f"--model {m}" for m in models() + ["diffuse"]),
    threads: WORKERS
    log:
        "logs/fit/{sid}/best.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} best --out {params.out} {params.models}"
        " --figures {params.figures} {params.cfg} --workers {threads} 2> {log}"


rule holdout:
    input:
        capture=capture_dir,
        poses=f"{PROC}/{{sid}}/camera/poses.yaml",
        radiometry=f"{PROC}/{{sid}}/camera/radiometry.json",
        params=lambda wc: expand(f"{PROC}/{wc.sid}/params/{{m}}.exr", m=compared_models()),
    output:
        metrics=f"{PROC}/{{sid}}/metrics/holdout.json",
        images=directory(f"{PROC}/{{sid}}/holdout"),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        models=" ".join(f"--model {m}" for m in compared_models()),
    log:
        "logs/holdout/{sid}.log",
    benchmark:
        "logs/benchmarks/{sid}/holdout.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} holdout {input.capture} --out {params.out} {params.models} 2> {log}"
