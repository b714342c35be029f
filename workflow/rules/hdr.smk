# HDR stage: one response per capture, then every view merged in its own job (memory
# bounded by one bracket), then the per-view figures gathered into metrics/hdr.json.


rule response:
    input:
        capture=capture_dir,
        ok=f"{PROC}/{{sid}}/capture.ok",
    output:
        csv=f"{PROC}/{{sid}}/camera/response.csv",
        figure=report(
            f"{REPORTS}/{{sid}}/response.png",
            caption="../report/response.rst",
            category="Capture",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        cfg=config_arg("hdr"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        reference=lambda wc: (
            f"--reference {CAPTURES[wc.sid]}.truth/response.npz --reference-label truth"
            if wc.sid in SYNTH
            else ""
        ),
    log:
        "logs/response/{sid}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} response {input.capture} --out {params.out} {params.cfg}"
        " --figure {output.figure} {params.reference} 2> {log}"


rule hdr_view:
    input:
        capture=capture_dir,
        response=f"{PROC}/{{sid}}/camera/response.csv",
    output:
        exr=f"{PROC}/{{sid}}/hdr/{{view}}.exr",
        stats=f"{PROC}/{{sid}}/hdr/{{view}}.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("hdr"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    log:
        "logs/hdr/{sid}/{view}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} hdr {input.capture} --out {params.out} --response {input.response}"
        " --view {wildcards.view} {params.cfg} 2> {log}"


rule hdr_metrics:
    input:
        stats=lambda wc: expand(f"{PROC}/{wc.sid}/hdr/{{view}}.json", view=view_ids(wc)),
    output:
        metrics=f"{PROC}/{{sid}}/metrics/hdr.json",
        figure=report(
            f"{REPORTS}/{{sid}}/reexposure.png",
            caption="../report/reexposure.rst",
            category="Capture",
            subcategory="{sid}",
        ),
    log:
        "logs/hdr/{sid}/metrics.log",
    conda:
        "../envs/parammap.yaml"
    script:
        "../scripts/gather_hdr.py"


rule calibrate:
    input:
        capture=capture_dir,
        ok=f"{PROC}/{{sid}}/capture.ok",
    output:
        f"{PROC}/{{sid}}/camera/intrinsics.yaml",
        f"{PROC}/{{sid}}/metrics/calibration.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("calibration"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    log:
        "logs/calibrate/{sid}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} calibrate {input.capture} --out {params.out} {params.cfg}"
        " 2> {log}"


rule poses:
    input:
        capture=capture_dir,
        intrinsics=f"{PROC}/{{sid}}/camera/intrinsics.yaml",
        hdr=lambda wc: expand(f"{PROC}/{wc.sid}/hdr/{{view}}.exr", view=view_ids(wc)),
    output:
        f"{PROC}/{{sid}}/camera/poses.yaml",
        f"{PROC}/{{sid}}/metrics/poses.json",
        report(
            f"{REPORTS}/{{sid}}/view_directions.png",
            caption="../report/view_directions.rst",
            category="Capture",
            subcategory="{sid}",
        ),
        f"{REPORTS}/{{sid}}/pose_reprojection.png",
    params:
        cli=PARAMMAP,
        cfg=config_arg("poses"),
        out=lambda wc: f"{PROC}/{wc.sid}",
        figures=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        "logs/poses/{sid}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} poses {input.capture} --out {params.out} {params.cfg}"
        " --figures {params.figures} 2> {log}"
