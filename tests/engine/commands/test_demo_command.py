"""`kneegui demo`: writes the demo deck and its setup."""

from kneegui.cli import main


def test_cli_demo_writes_both_files(tmp_path):
    assert main(["demo", str(tmp_path), "--elements", "3000", "--side", "left"]) == 0
    assert (tmp_path / "demo_leg.k").stat().st_size > 0
    assert '"side": "left"' in (tmp_path / "demo_leg.setup.json").read_text()
