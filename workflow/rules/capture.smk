# Capture stage: synthesise the configured synthetic captures when missing, validate
# every capture and draw its summary.


rule synth:
    output:
        capture=directory("{capdir}"),
    params:
        cli=PARAMMAP,
        preset=lambda wc: synth_for(wc.capdir)["preset"],
        seed=lambda wc: synth_for(wc.capdir)["seed"],
        sid=lambda wc: synth_sid(wc.capdir),
    threads: WORKERS
    log:
        "logs/synth/{capdir}.log",
    wildcard_constraints:
        capdir=SYNTH_DIRS_RE,
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} synth --preset {params.preset} --seed {params.seed} --id {params.sid}"
        " --out {output.capture} --workers {threads} 2> {log}"


checkpoint validate_capture:
    input:
        capture_dir,
    output:
        f"{PROC}/{{sid}}/capture.ok",
    params:
        cli=PARAMMAP,
    log:
        f"logs/validate/{{sid}}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} validate-capture {input} > {output} 2> {log}"


rule capture_summary:
    input:
        capture=capture_dir,
        ok=rules.validate_capture.output,
    output:
        report(
            f"{REPORTS}/{{sid}}/contact_sheet.png",
            caption="../report/contact_sheet.rst",
            category="Capture",
            subcategory="{sid}",
        ),
    params:
        cli=PARAMMAP,
        out=lambda wc: f"{REPORTS}/{wc.sid}",
    log:
        f"logs/summary/{{sid}}.log",
    conda:
        "../envs/parammap.yaml"
    shell:
        "{params.cli} summary {input.capture} --out {params.out} 2> {log}"
