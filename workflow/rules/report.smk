# Report figures and tables, built only from stage outputs: deleting reports/ and
# running the workflow again rebuilds them without refitting anything.
from pathlib import Path


rule fig_response:
    input:
        capture=capture_dir,
        csv=f"{PROC}/{{sid}}/camera/response.csv",
    output:
        report(
            f"{REPORTS}/{{sid}}/response.png",
            caption="../report/response.rst",
            category="1 Capture",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
        reference=lambda wc: (
            f"--reference {CAPTURES[wc.sid]}.truth/response.npz --reference-label truth"
            if wc.sid in SYNTH
            else ""
        ),
    log:
        "logs/figures/{sid}/response.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures response {input.capture} --out {params.out}"
        " --figures {params.figures} {params.reference} 2> {log}"


rule fig_hdr:
    input:
        capture=capture_dir,
        metrics=f"{PROC}/{{sid}}/metrics/hdr.json",
    output:
        report(
            f"{REPORTS}/{{sid}}/reexposure.png",
            caption="../report/reexposure.rst",
            category="1 Capture",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/figures/{sid}/hdr.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures hdr {input.capture} --out {params.out} --figures {params.figures}"
        " 2> {log}"


rule fig_radiometry:
    input:
        capture=capture_dir,
        radiometry=f"{PROC}/{{sid}}/camera/radiometry.json",
        metrics=f"{PROC}/{{sid}}/metrics/radiometry.json",
    output:
        report(
            f"{REPORTS}/{{sid}}/radiometry.png",
            caption="../report/radiometry.rst",
            category="1 Capture",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/figures/{sid}/radiometry.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures radiometry {input.capture} --out {params.out}"
        " --figures {params.figures} 2> {log}"


rule fig_calibration:
    input:
        capture=capture_dir,
        metrics=f"{PROC}/{{sid}}/metrics/calibration.json",
    output:
        report(
            f"{REPORTS}/{{sid}}/calibration.png",
            caption="../report/calibration.rst",
            category="1 Capture",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/figures/{sid}/calibration.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures calibration {input.capture} --out {params.out}"
        " --figures {params.figures} 2> {log}"


rule fig_poses:
    input:
        capture=capture_dir,
        poses=f"{PROC}/{{sid}}/camera/poses.yaml",
    output:
        directions=report(
            f"{REPORTS}/{{sid}}/view_directions.png",
            caption="../report/view_directions.rst",
            category="1 Capture",
            subcategory="{sid}",
        ),
        reprojection=report(
            f"{REPORTS}/{{sid}}/pose_reprojection.png",
            caption="../report/pose_reprojection.rst",
            category="1 Capture",
            subcategory="{sid}",
        ),
        table=report(
            f"{REPORTS}/{{sid}}/poses.csv",
            caption="../report/poses_table.rst",
            category="1 Capture",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/figures/{sid}/poses.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures poses {input.capture} --out {params.out}"
        " --figures {params.figures} 2> {log}"


rule fig_observation:
    input:
        capture=capture_dir,
        obs=f"{PROC}/{{sid}}/observation.zarr",
    output:
        counts=report(
            f"{REPORTS}/{{sid}}/observation_valid_count.png",
            caption="../report/observation_valid_count.rst",
            category="2 Observation map",
            subcategory="{sid}",
        ),
        lobes=report(
            f"{REPORTS}/{{sid}}/observation_lobes.png",
            caption="../report/observation_lobes.rst",
            category="2 Observation map",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("observation"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/figures/{sid}/observation.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures observation {input.capture} --out {params.out}"
        " --figures {params.figures} {params.cfg} 2> {log}"


rule fig_model:
    input:
        capture=capture_dir,
        fit=f"{PROC}/{{sid}}/fit/{{model}}.zarr",
        obs=f"{PROC}/{{sid}}/observation.zarr",
    output:
        params=report(
            f"{REPORTS}/{{sid}}/{{model}}_params.png",
            caption="../report/model_params.rst",
            category="3 Models",
            subcategory="{sid}",
        ),
        residuals=report(
            f"{REPORTS}/{{sid}}/{{model}}_residuals.png",
            caption="../report/model_residuals.rst",
            category="3 Models",
            subcategory="{sid}",
        ),
        lobes=report(
            f"{REPORTS}/{{sid}}/{{model}}_lobes.png",
            caption="../report/model_lobes.rst",
            category="3 Models",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("observation"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    wildcard_constraints:
        model="(mh|sh|svbrdf)-[a-z0-9-]+",
    log:
        "logs/figures/{sid}/{model}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures model {input.capture} --out {params.out} --model {wildcards.model}"
        " --figures {params.figures} {params.cfg} 2> {log}"


rule advise:
    input:
        obs=f"{PROC}/{{sid}}/observation.zarr",
        poses=f"{PROC}/{{sid}}/camera/poses.yaml",
        source=lambda wc: f"{PROC}/{wc.sid}/fit/{mh_source('advisor')}.zarr",
    output:
        metrics=f"{PROC}/{{sid}}/metrics/advice.json",
        figure=report(
            f"{REPORTS}/{{sid}}/advice.png",
            caption="../report/advice.rst",
            category="5 Next capture",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("advisor", "observation"),
        source=lambda wc: mh_source("advisor"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/figures/{sid}/advice.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} advise --out {params.out} --figures {params.figures}"
        " {params.cfg} --set advisor.source={params.source} 2> {log}"


rule lights:
    input:
        capture=capture_dir,
        source=lambda wc: f"{PROC}/{wc.sid}/fit/{mh_source('lights')}.zarr",
    output:
        lights=f"{PROC}/{{sid}}/camera/lights.yaml",
        metrics=f"{PROC}/{{sid}}/metrics/lights.json",
        figure=report(
            f"{REPORTS}/{{sid}}/lights.png",
            caption="../report/lights.rst",
            category="6 Lights",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("lights"),
        source=lambda wc: mh_source("lights"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/figures/{sid}/lights.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} lights --out {params.out} --figures {params.figures}"
        " --capture {input.capture} {params.cfg} --set lights.source={params.source}"
        " 2> {log}"


rule fig_holdout:
    input:
        capture=capture_dir,
        metrics=f"{PROC}/{{sid}}/metrics/holdout.json",
        images=f"{PROC}/{{sid}}/holdout",
    output:
        table=report(
            f"{REPORTS}/{{sid}}/holdout.csv",
            caption="../report/holdout_table.rst",
            category="4 Held-out photos",
            subcategory="{sid}",
        ),
        regions=report(
            f"{REPORTS}/{{sid}}/holdout_regions.csv",
            caption="../report/holdout_regions.rst",
            category="4 Held-out photos",
            subcategory="{sid}",
        ),
        panels=report(
            directory(f"{REPORTS}/{{sid}}/holdout"),
            patterns=["{view}.png"],
            caption="../report/holdout_panels.rst",
            category="4 Held-out photos",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/figures/{sid}/holdout.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures holdout {input.capture} --out {params.out}"
        " --figures {params.figures} 2> {log}"


rule fig_tables:
    input:
        capture=capture_dir,
        obs=f"{PROC}/{{sid}}/metrics/observation.json",
        fits=lambda wc: expand(f"{PROC}/{wc.sid}/metrics/fit-{{m}}.json", m=models()),
        params=lambda wc: expand(f"{PROC}/{wc.sid}/params/{{m}}.exr", m=models()),
        holdout=f"{PROC}/{{sid}}/metrics/holdout.json",
        timings=lambda wc: benchmark_files(wc.sid),
    output:
        sizes=report(
            f"{REPORTS}/{{sid}}/sizes.csv",
            caption="../report/sizes.rst",
            category="5 Tables",
            subcategory="{sid}",
        ),
        models=report(
            f"{REPORTS}/{{sid}}/models.csv",
            caption="../report/models.rst",
            category="5 Tables",
            subcategory="{sid}",
        ),
        timings=report(
            f"{REPORTS}/{{sid}}/timings.csv",
            caption="../report/timings.rst",
            category="5 Tables",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
        models=lambda wc: " ".join(models()),
    log:
        "logs/figures/{sid}/tables.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} figures tables {input.capture} --out {params.out}"
        " --figures {params.figures} --models {params.models}"
        " --timings {input.timings} 2> {log}"


rule viewer:
    input:
        capture=capture_dir,
        poses=f"{PROC}/{{sid}}/camera/poses.yaml",
        holdout=f"{PROC}/{{sid}}/metrics/holdout.json",
        params=lambda wc: expand(f"{PROC}/{wc.sid}/params/{{m}}.exr", m=compared_models()),
        obs=f"{PROC}/{{sid}}/observation.zarr",  # the texel inspector's observations
    output:
        directory(f"{REPORTS}/{{sid}}/viewer"),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{PROC}/{wc.sid}",
        models=" ".join(f"--model {m}" for m in compared_models()),
    log:
        "logs/figures/{sid}/viewer.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} viewer {input.capture} --out {params.out} --figures {output}"
        " {params.models} 2> {log}"


rule batch_summary:
    input:
        metrics=lambda wc: [f"{PROC}/{sid}/metrics/{m}.json" for sid in CAPTURES
                            for m in ["poses", "calibration", "observation", "holdout"]
                            + [f"fit-{x}" for x in models()]],
    output:
        csv=report(f"{REPORTS}/summary.csv", caption="../report/summary.rst",
                   category="0 Run summary"),
        png=report(f"{REPORTS}/summary.png", caption="../report/summary.rst",
                   category="0 Run summary"),
    params:
        cli=PARAMMAP,
        root=PROC,
        surfaces=" ".join(f"--surface {sid}" for sid in CAPTURES),
        models=" ".join(f"--model {m}" for m in models()),
        out=lambda wc, output: str(Path(output.csv).parent),
    log:
        "logs/figures/summary.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} batch-summary --processed {params.root} {params.surfaces}"
        " {params.models} --out {params.out} 2> {log}"
