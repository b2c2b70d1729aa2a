"""The shipped scenarios (`rbdyn_jax/scenarios/*.toml`) by name and description, read
straight from their files without JAX, for `rbdyn scenarios`; `scenario.Scenario.load`
validates one and builds it."""

import pathlib
import tomllib

SCENARIO_DIR = pathlib.Path(__file__).parent / "scenarios"


def list_scenarios() -> list[str]:
    """Names of the scenarios shipped in `rbdyn_jax/scenarios/`."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def catalogue() -> dict[str, str]:
    """`{name: description}` of every shipped scenario, in name order: the `description`
    its file gives (`""` if none), as `Scenario.load(name).description` reads it."""
    return {
        name: tomllib.loads((SCENARIO_DIR / f"{name}.toml").read_text()).get("description", "")
        for name in list_scenarios()
    }
