# HDR and camera stages: one response per capture, every view merged in its own job
# (memory bounded by one bracket), per-view figures gathered into metrics/hdr.json;
# intrinsics from the board photos; the pose of every view from the surface markers;
# the flat-field and colour correction from the white card and colour chart.
# Figures come from report.smk, never from these jobs.


rule response:
    input:
        capture=capture_dir,
        ok=f"{PROC}/{{sid}}/capture.ok",
    output:
        f"{PROC}/{{sid}}/camera/response.csv",
    params:
        cli=PARAMMAP,
        cfg=config_arg("hdr"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    log:
        "logs/response/{sid}.log",
    benchmark:
        "logs/benchmarks/{sid}/response.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} response {input.capture} --out {params.out} {params.cfg} 2> {log}"


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
        hdr=lambda wc: (
            expand(f"{PROC}/{wc.sid}/hdr/{{view}}.exr", view=fitted_view_ids(wc))
            if config["calibration"]["use_marker_views"]
            else []
        ),
    output:
        f"{PROC}/{{sid}}/camera/intrinsics.yaml",
        f"{PROC}/{{sid}}/metrics/calibration.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("calibration"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    threads: WORKERS
    log:
        "logs/calibrate/{sid}.log",
    benchmark:
        "logs/benchmarks/{sid}/calibrate.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} calibrate {input.capture} --out {params.out} {params.cfg}"
        " --workers {threads} 2> {log}"


rule radiometry:
    input:
        capture=capture_dir,
        intrinsics=f"{PROC}/{{sid}}/camera/intrinsics.yaml",
        hdr=lambda wc: expand(f"{PROC}/{wc.sid}/hdr/{{view}}.exr",
                              view=radiometry_view_ids(wc)),
    output:
        f"{PROC}/{{sid}}/camera/radiometry.json",
        f"{PROC}/{{sid}}/metrics/radiometry.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("radiometry"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    log:
        "logs/radiometry/{sid}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} radiometry {input.capture} --out {params.out} {params.cfg} 2> {log}"


rule poses:
    input:
        capture=capture_dir,
        intrinsics=f"{PROC}/{{sid}}/camera/intrinsics.yaml",
        hdr=lambda wc: expand(f"{PROC}/{wc.sid}/hdr/{{view}}.exr", view=view_ids(wc)),
    output:
        f"{PROC}/{{sid}}/camera/poses.yaml",
        f"{PROC}/{{sid}}/metrics/poses.json",
    params:
        cli=PARAMMAP,
        cfg=config_arg("poses", "observation"),
        out=lambda wc: f"{PROC}/{wc.sid}",
    threads: WORKERS
    log:
        "logs/poses/{sid}.log",
    benchmark:
        "logs/benchmarks/{sid}/poses.tsv"
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} poses {input.capture} --out {params.out} {params.cfg}"
        " --workers {threads} 2> {log}"
