"""Reports, benchmarks, studies and reference implementations
(`dcdi report ...`, `dcdi bench ...`): they use the engine; the engine never
imports them, and the Blender add-on does not bundle them.

- ``psf_accuracy``, ``simulation_accuracy``, ``resample_accuracy``,
  ``olf_report``, ``psf_source_report``, ``pipeline_report``: error against
  run time;
- ``bench``, ``bench_defocus``: times and ratios against a baseline run in
  the same process; the lens bokeh beside Blender's Defocus node;
- ``bokeh_reference``: the per-pixel scatter bokeh the layered one is scored against;
- ``dacn_study``, ``olf_sweep``: the runs that chose the shipped networks.
"""


def write_report(out, stem: str, result: dict, markdown: str, plot, log) -> None:
    """A report's files into folder ``out``: STEM.json (``result``), STEM.md
    (``markdown``, also logged) and STEM-error-vs-storage.png (``plot(result,
    path)``)."""
    import json
    from pathlib import Path

    from ..atomic import write_text
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    png = out / f"{stem}-error-vs-storage.png"
    write_text(out / f"{stem}.json", json.dumps(result, indent=1, default=float) + "\n")
    write_text(out / f"{stem}.md", markdown)
    plot(result, png)
    log(markdown)
    log(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')} and {png}")
