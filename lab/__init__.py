"""The lab: studies, reports, benchmarks against references and reference
implementations that make the figures and tables of docs/, and the configs
that remake the shipped networks (``configs/``, ``python -m lab reproduce``).
They use the engine (``dcdi_core``); the engine never imports them, and
neither the wheel nor the Blender extension carries them. Run from the
repository's root: ``python -m lab ...`` (``lab/cli.py``; lab/README.md lists
each study and the command that makes each figure).

- ``psf_accuracy``, ``simulation_accuracy``, ``resample_accuracy``,
  ``olf_report``, ``psf_source_report``, ``pipeline_report``,
  ``correction_report``, ``depth_from_blur_report``,
  ``capture_record_report``: error against run time;
- ``bench_defocus``, ``bokeh_variants``: the lens bokeh beside Blender's
  Defocus node (``thin_lens``: the node's thin lens; ``defocus_node``: the
  node under pip bpy) and the bokeh's variants;
- ``bokeh_reference``: the per-pixel scatter bokeh the layered one is scored against;
- ``dacn_study``, ``dfd_refine_study``, ``olf_sweep``: the runs that chose the
  shipped networks; ``reproduce``: those networks from their configs;
- ``cli_reference``: docs/cli.md from the `dcdi` command's parser.
"""


def write_report(out, stem: str, result: dict, markdown: str, plot, log) -> None:
    """A report's files into folder ``out``: STEM.json (``result``), STEM.md
    (``markdown``, also logged) and STEM-error-vs-storage.png (``plot(result,
    path)``)."""
    import json
    from pathlib import Path

    from dcdi_core.atomic import write_text
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    png = out / f"{stem}-error-vs-storage.png"
    write_text(out / f"{stem}.json", json.dumps(result, indent=1, default=float) + "\n")
    write_text(out / f"{stem}.md", markdown)
    plot(result, png)
    log(markdown)
    log(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')} and {png}")
