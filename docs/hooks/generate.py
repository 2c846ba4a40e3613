"""mkdocs hook: the pages generated from the code (the CLI reference from argparse) and the source
layout mkdocstrings reads (`skinsafe.core` lives in core/, and so on)."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = {"core": "core", "exporters": "exporters", "hardware": "hardware", "addon": "addon"}


def _api_source() -> None:
    """build/api-src/skinsafe/{core,...} -> the folders (made on import: mkdocstrings reads the path first)."""
    src = ROOT / "build" / "api-src" / "skinsafe"
    src.mkdir(parents=True, exist_ok=True)
    (src / "__init__.py").write_text('"""skinsafe: whole-body tactile skins, from Blender to the robot."""\n')
    for name, folder in PACKAGES.items():
        link = src / name
        if not link.is_symlink():
            link.symlink_to(ROOT / folder, target_is_directory=True)


_api_source()


def on_page_markdown(markdown, page, config, files):
    if "<!-- cli-reference -->" in markdown:
        from skinsafe.core.app.cli import reference_markdown

        markdown = markdown.replace("<!-- cli-reference -->", reference_markdown())
    return _assets_from(markdown, page)


ASSETS = ("results/", "blend_assets/")
ASSET_REF = re.compile(r'(\]\(|src=")((?:results|blend_assets)/[^)"\s]+)')


def on_files(files, config):
    """The pictures pages show from results/ and blend_assets/, served at the same paths."""
    from mkdocs.structure.files import File

    for folder in ("results", "blend_assets/pictures"):
        for path in sorted((ROOT / folder).rglob("*.png")):
            rel = path.relative_to(ROOT).as_posix()
            files.append(File(rel, str(ROOT), config["site_dir"], config["use_directory_urls"]))
    return files


def _assets_from(markdown: str, page) -> str:
    """`results/x.png` in a page at docs/a/b.md points to the site root's results/x.png."""
    up = "../" * page.file.src_uri.count("/")
    return ASSET_REF.sub(lambda m: m.group(1) + up + m.group(2), markdown)
