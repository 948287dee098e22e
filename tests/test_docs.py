"""The claims the README and the packaging files make about the project, checked against the files.

The conda environment pins what pyproject.toml pins; the README stays a landing page; every relative link
in README.md and docs/*.md reaches a file (and a heading, when it names one); licence, citation and
version agree across LICENSE, CITATION.cff, pyproject.toml and the package.
"""

import re
import tomllib
from pathlib import Path

import pytest
import yaml
from packaging.markers import Marker
from packaging.specifiers import SpecifierSet

import deeptissue

ROOT = Path(__file__).resolve().parents[1]
README_MAX_CHARS = 12_000
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PIN = re.compile(r"^([A-Za-z0-9][A-Za-z0-9._-]*)==([^\s;,]+)$")
# [text](target) and ![alt](target); the target ends at whitespace or the closing parenthesis
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())


def _pins(requirements: list[str], where: str) -> dict[str, str]:
    """{normalised name: "version; marker"} of `name==version[; marker]` lines; anything else is a test
    failure (a platform marker, such as MKL's x86-64 only, must be the same in both files)."""
    pins = {}
    for req in requirements:
        text, _, marker = req.partition(";")
        match = PIN.match(text.strip())
        assert match, f"{where}: {req!r} is not pinned as name==version"
        name = re.sub(r"[-_.]+", "-", match.group(1)).lower()
        assert name not in pins, f"{where}: {name} is listed twice"
        pins[name] = match.group(2) + (f"; {Marker(marker.strip())}" if marker.strip() else "")
    return pins


def test_conda_env_pins_equal_pyproject():
    project = _pyproject()["project"]
    expected = _pins(
        project["dependencies"] + project["optional-dependencies"]["slurm"],
        "pyproject.toml [project] dependencies + slurm extra",
    )
    env = yaml.safe_load((ROOT / "workflow" / "envs" / "deeptissue.yaml").read_text())
    pip = next(d["pip"] for d in env["dependencies"] if isinstance(d, dict) and "pip" in d)
    actual = _pins(pip, "workflow/envs/deeptissue.yaml pip section")
    missing = sorted(set(expected) - set(actual))
    extra = sorted(set(actual) - set(expected))
    differ = {
        k: (actual[k], expected[k])
        for k in set(expected) & set(actual)
        if actual[k] != expected[k]
    }
    assert not (missing or extra or differ), (
        f"workflow/envs/deeptissue.yaml differs from pyproject.toml: missing {missing}, "
        f"not in pyproject {extra}, other pins (env, pyproject) {differ}; copy the pins of "
        "pyproject.toml's dependencies and its slurm extra into the env's pip section"
    )
    python = next(d for d in env["dependencies"] if isinstance(d, str) and d.startswith("python="))
    assert python.split("=", 1)[1] in SpecifierSet(project["requires-python"])


def test_readme_is_a_landing_page():
    n = len((ROOT / "README.md").read_text())
    assert n <= README_MAX_CHARS, (
        f"README.md has {n} characters, more than {README_MAX_CHARS}: move the detail to docs/usage.md"
    )


def _slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*]|\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _unfenced(text: str) -> str:
    """The page without its fenced code blocks (a `#` line there is no heading)."""
    return re.sub(r"^(```|~~~).*?^\1[^\n]*$", "", text, flags=re.M | re.S)


def _outside_code(text: str) -> str:
    """The page without code blocks and inline code spans (a link written there is not a link)."""
    return re.sub(r"`[^`\n]*`", "", _unfenced(text))


def _anchors(page: Path) -> set[str]:
    anchors, seen = set(), {}
    for line in _unfenced(page.read_text()).splitlines():
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match:
            slug = _slug(match.group(1))
            anchors.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
            seen[slug] = seen.get(slug, 0) + 1
    return anchors


def test_slug_follows_github():
    assert _slug("7. Strain, VOI and bins") == "7-strain-voi-and-bins"
    assert _slug("Adaptive study (`config/adaptive.yaml`)") == "adaptive-study-configadaptiveyaml"
    assert _slug("Limb variants (rule `adapt_variant`)") == "limb-variants-rule-adapt_variant"
    assert _slug("Stop, resume, share a results folder") == "stop-resume-share-a-results-folder"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_reach_a_file_and_heading(page):
    broken = []
    for target in LINK.findall(_outside_code(page.read_text())):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            broken.append(f"{target} (no file {dest.relative_to(ROOT)})")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target} (no heading #{anchor} in {dest.relative_to(ROOT)})")
    assert not broken, f"{page.relative_to(ROOT)}: broken links: {broken}"


def test_licence_citation_and_version_agree():
    project = _pyproject()["project"]
    citation = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    licence = (ROOT / "LICENSE").read_text()
    assert project["license"] == citation["license"] == "BSD-3-Clause"
    assert project["license-files"] == ["LICENSE"]
    assert licence.startswith("BSD 3-Clause License")
    assert "Neither the name of the copyright holder" in licence  # clause 3, not the 2-clause text
    assert project["version"] == str(citation["version"]) == deeptissue.__version__
    assert citation["cff-version"] == "1.2.0"
    for key in ("message", "title", "authors"):
        assert citation[key], f"CITATION.cff: {key} is required"
    (paper,) = [r for r in citation["references"] if r["type"] == "article"]
    assert paper["authors"][0]["family-names"] == "Traa" and paper["year"] == 2018
