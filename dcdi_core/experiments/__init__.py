"""Reports, benchmarks, studies and reference implementations
(`dcdi report ...`, `dcdi bench ...`): they use the engine; the engine never
imports them, and the Blender add-on does not bundle them.

- ``psf_accuracy``, ``simulation_accuracy``, ``resample_accuracy``,
  ``olf_report``, ``pipeline_report``: error against run time;
- ``bench``, ``bench_defocus``: times and ratios against a baseline run in
  the same process; the lens bokeh beside Blender's Defocus node;
- ``bokeh_reference``: the per-pixel scatter bokeh the layered one is scored against;
- ``dacn_study``, ``olf_sweep``: the runs that chose the shipped networks.
"""
