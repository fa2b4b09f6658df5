"""Reports name no absolute path of the machine that wrote them (core.paths)."""

from __future__ import annotations

from pathlib import Path

from mfg_lightning.core.paths import portable_overrides, portable_path


def test_absolute_paths_become_relative_or_placeholders(tmp_path: Path) -> None:
    repo, cache = tmp_path / "repo", tmp_path / "home" / ".cache" / "mfg"
    assert portable_path(str(repo / "bench" / "a.py"), repo, cache) == "bench/a.py"
    assert portable_path(str(tmp_path / "shared" / "poses"), repo, cache) == "../shared/poses"
    # the cache sits beside the repository here too: the closer root (..) wins, as a reader
    # standing in the repository would find it
    assert portable_path(str(cache / "x"), repo, cache) == "../home/.cache/mfg/x"
    assert portable_path("/elsewhere/file", repo, cache) == "<path>"
    assert portable_path("/elsewhere/file", repo) == "<path>"
    for text in ("relative/dir", "--tiny", "0.05", "[1,2]"):
        assert portable_path(text, repo, cache) == text


def test_cache_placeholder_and_overrides(tmp_path: Path) -> None:
    repo = tmp_path / "work" / "repo"
    cache = Path("/var/cache/mfg")
    got = portable_overrides(
        [f"dataset.cache_dir={cache}/flow", f"dataset.poses_dir={tmp_path}/work/shared/p",
         "flow=dis", "dataset.offsets=[-1,1]", "+x"],
        repo, cache,
    )  # fmt: skip
    assert got == ["dataset.cache_dir=<cache>/flow", "dataset.poses_dir=../shared/p", "flow=dis",
                   "dataset.offsets=[-1,1]", "+x"]  # fmt: skip
