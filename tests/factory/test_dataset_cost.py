"""The factory data set's cost summary (JSON only, no bpy)."""
import json

from blender_addon.tools.dataset_cost import main, summary


def test_cost_summary_means_and_shares(tmp_path, capsys):
    recs = [{"id": f"room-{i}", "recipe": "room", "seconds": 10.0 + i, "cpu_seconds": 20.0,
             "stage_seconds": {"cpu_render": 15.0}} for i in range(3)]
    (tmp_path / "manifest.jsonl").write_text("\n".join(json.dumps(r) for r in recs) + "\n{torn")
    s = summary(recs)
    assert s["samples"] == 3 and s["wall_s"] == 11.0 and s["cpu_s"] == 20.0 and s["render_cpu_share"] == 0.75
    assert main([str(tmp_path)]) == 0
    assert "| room | 3 | 11.0 | 20.0 | 75 % |" in capsys.readouterr().out
