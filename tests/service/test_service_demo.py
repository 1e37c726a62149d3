"""`hapticlink demo` end to end, at a small size: assets from nothing, service, robot, printed estimates."""

import asyncio

from models.offline.demo_assets import prepare_assets
from service.demo import run_demo


def test_demo_builds_its_assets_and_streams_estimates(tmp_path, kit, capsys):
    assets = prepare_assets(tmp_path / "demo", n_textures=5, n_probes=2)
    for path in (assets.model, assets.backbone, assets.library / "library.json", assets.probes / "library.json"):
        assert path.is_file(), path
    asyncio.run(run_demo(assets, host="127.0.0.1", port=kit.free_port(), per_texture_s=3.0, duration_s=7.0))
    out = capsys.readouterr().out
    assert "/console?session=" in out and "token=" in out
    assert "stroking synth_000: estimate" in out and "nearest library texture:" in out
    assert "'lost': 0" in out and "'unsent': 0" in out
