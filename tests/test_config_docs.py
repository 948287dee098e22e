"""docs/config.md is the schema rendered by deeptissue.config.schema_markdown; the cross-key config checks."""

import copy
from pathlib import Path

import pytest
import yaml

from deeptissue.config import (
    REGENERATE_COMMAND,
    ConfigError,
    animal_variants,
    check_config,
    convergence_animals,
    figure_animal,
    load_schema,
    main,
    schema_markdown,
    validate_config,
)

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"
DOCS = ROOT / "docs" / "config.md"

TINY = {
    "description": "A tiny configuration.",
    "type": "object",
    "required": ["name"],
    "properties": {
        "name": {"description": "Who it is.", "type": "string"},
        "solver": {
            "description": "Solver settings.",
            "type": "object",
            "properties": {
                "depth_mm": {
                    "description": "How deep | the tip goes.",
                    "unit": "mm",
                    "type": "number",
                    "exclusiveMinimum": 0,
                    "maximum": 5,
                    "default": 2.5,
                },
                "method": {"description": "Which way.", "enum": ["a", "b"], "default": "b"},
            },
        },
    },
}


def test_docs_config_md_is_the_schema_rendered():
    expected = schema_markdown(load_schema(SCHEMA))
    actual = DOCS.read_text() if DOCS.is_file() else ""
    assert actual == expected, (
        f"docs/config.md is out of date with the schema; regenerate it: {REGENERATE_COMMAND}"
    )


def test_every_schema_key_is_documented():
    text = DOCS.read_text()
    schema = load_schema(SCHEMA)

    def documented(path):  # a row of its section's table, or a section of its own
        return f"| `{path}` |" in text or f"## `{path}`" in text

    for section in ("segmentation", "pose", "model", "fem", "study", "convergence"):
        for key in schema["properties"][section]["properties"]:
            assert documented(f"{section}.{key}"), f"{section}.{key}"
    for key, sub in schema["properties"]["fem"]["properties"]["solver"]["properties"].items():
        for path in (
            [f"fem.solver.{key}.{k}" for k in sub["properties"]]
            if "properties" in sub
            else [f"fem.solver.{key}"]
        ):
            assert documented(path), path
    for key in schema["definitions"]["phantom"]["properties"]:
        assert documented(f"animals.<name>.phantom.{key}"), key


def test_renderer_on_a_tiny_schema():
    text = schema_markdown(TINY)
    assert "A tiny configuration." in text
    assert "## `solver`\n\nSolver settings." in text
    assert "| `name` | string | required |  |  | Who it is. |" in text
    # default, unit, range, and a pipe in the description escaped so the table keeps its columns
    assert (
        "| `solver.depth_mm` | number | `2.5` | `mm` | > 0; ≤ 5 | How deep \\| the tip goes. |"
        in text
    )
    assert '| `solver.method` | enum | `"b"` |  | one of `"a"`, `"b"` | Which way. |' in text
    assert text.endswith("\n") and not text.endswith("\n\n")


def test_main_writes_the_page(tmp_path):
    schema_path = tmp_path / "schema.yaml"
    schema_path.write_text(yaml.safe_dump(TINY))
    out = tmp_path / "docs" / "config.md"
    main([str(out), "--schema", str(schema_path)])
    assert out.read_text() == schema_markdown(TINY)


def _demo():
    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    return validate_config(cfg, SCHEMA, base_dir=ROOT)


@pytest.mark.parametrize(
    "mutate, match",
    [
        (
            lambda c: c["study"].update(threshold=0.25),
            r"config key study\.bin_edges: must start at study\.threshold \(0\.25\), got 0\.3",
        ),
        (
            lambda c: c["study"].update(bin_edges=[0.3, 0.5, 0.4]),
            r"config key study\.bin_edges: not strictly increasing: \[0\.3, 0\.5, 0\.4\]",
        ),
        (
            lambda c: c["study"].update(figure_animal="rat09"),
            r"config key study\.figure_animal: 'rat09' is not a configured animal",
        ),
        (
            lambda c: c["convergence"].update(animals=["rat01", "rat09"]),
            r"config key convergence\.animals: \['rat09'\] are not configured animals \[",
        ),
        (
            lambda c: c["animals"].update(
                calf={
                    "pre": "config/config.yaml",
                    "crop_mm": [[0, 1], [0, 1], [0, 1]],
                    "leg_point_mm": [0.5, 2.0, 0.5],
                }
            ),
            r"config key animals\.calf\.leg_point_mm: \[0\.5, 2\.0, 0\.5\] lies outside animals\.calf\.crop_mm",
        ),
        (  # an animal's own variants must hold the base of each turned one: it is compared with it
            lambda c: c["animals"]["rat01"].update(variants=["bar", "sphere_rx+15"]),
            r"config key animals\.rat01\.variants: 'sphere_rx\+15' is turned from 'sphere', which the list "
            r"\['bar', 'sphere_rx\+15'\] does not name; add 'sphere'",
        ),
        (
            lambda c: c["animals"]["rat01"].update(variants=["sphere", "bar_rz-7.5"]),
            r"config key animals\.rat01\.variants: 'bar_rz-7\.5' is turned from 'bar'",
        ),
        (
            lambda c: c["animals"].update(
                calf={"pre": "config/config.yaml", "variants": ["sphere"]}
            ),
            r"config key animals\.calf\.variants: 'calf' has no during scan, so none of its variants is solved",
        ),
    ],
)
def test_cross_key_checks_name_the_key(mutate, match):
    cfg = _demo()
    check_config(copy.deepcopy(cfg))  # the demo passes
    mutate(cfg)
    with pytest.raises(ConfigError, match=match) as info:
        check_config(cfg)
    assert "\n" not in str(info.value)
    # validate_config runs the same checks
    with pytest.raises(ConfigError, match=match):
        validate_config(cfg, SCHEMA, base_dir=ROOT)


def test_figure_and_convergence_animals_defaults():
    cfg = _demo()
    assert figure_animal(cfg) == "rat01" and convergence_animals(cfg) == ["rat03", "rat02"]
    cfg["study"]["figure_animal"] = "rat03"
    cfg["convergence"]["animals"] = None
    assert figure_animal(cfg) == "rat03" and convergence_animals(cfg) == ["rat01"]
    # an animal without a during scan is skipped; with none, only the convergence target needs one
    cfg = validate_config(
        {"animals": {"calf": {"pre": "config/config.yaml"}}}, SCHEMA, base_dir=ROOT
    )
    assert figure_animal(cfg) is None and convergence_animals(cfg) == []
    cfg["study"]["figure_animal"] = "calf"
    with pytest.raises(
        ConfigError, match=r"config key study\.figure_animal: 'calf' has no during scan"
    ):
        check_config(cfg)
    cfg["study"]["figure_animal"] = None
    with pytest.raises(
        ConfigError,
        match=r"config key convergence\.animals: null, and no configured animal has a during scan",
    ):
        convergence_animals(cfg, required=True)
    # a study of pre-only animals is valid with the animal named too: only the convergence target refuses it
    cfg["convergence"]["animals"] = ["calf"]
    check_config(cfg)
    assert convergence_animals(cfg) == []
    with pytest.raises(
        ConfigError,
        match=r"config key convergence\.animals: \['calf'\] have no during scan; the "
        r"convergence target solves an indentation and needs animals with one",
    ):
        convergence_animals(cfg, required=True)
    cfg["convergence"]["animals"] = None
    cfg["animals"] = {"calf": {"pre": "a.nii.gz"}, "rat": {"phantom": {}}}
    assert convergence_animals(cfg) == ["rat"]


def test_an_animals_own_variants_replace_the_studys_for_it_alone():
    cfg = _demo()
    six = ["sphere", "bar", "sphere_rx+15", "sphere_rx-15", "sphere_rz+15", "sphere_rz-15"]
    assert [animal_variants(cfg, a) for a in cfg["animals"]] == [six, six, six]
    cfg["animals"]["rat02"]["variants"] = ["sphere_rz+15", "sphere"]
    cfg = validate_config(cfg, SCHEMA, base_dir=ROOT)
    assert animal_variants(cfg, "rat02") == ["sphere_rz+15", "sphere"]  # its own order
    assert animal_variants(cfg, "rat01") == six == cfg["study"]["variants"]
    # each item is checked as study.variants' are, with the animal's key in the message
    for bad, match in [
        (["sphere", "cone"], r"animals\.rat02\.variants\[1\]: 'cone' does not match"),
        ([], r"animals\.rat02\.variants: \[\] should be non-empty"),
        (["sphere", "sphere"], r"animals\.rat02\.variants: .* has non-unique elements"),
    ]:
        cfg["animals"]["rat02"]["variants"] = bad
        with pytest.raises(ConfigError, match=match):
            validate_config(cfg, SCHEMA, base_dir=ROOT)
