from __future__ import annotations

import pytest

from shared.scenario import Scenario, load_scenario


@pytest.fixture(scope="session")
def scenario() -> Scenario:
    return load_scenario()


def variant(base: Scenario, **sections) -> Scenario:
    """A copy of ``base`` with some fields of some sections replaced."""
    data = base.model_dump()
    for section, values in sections.items():
        data[section].update(values)
    return Scenario.model_validate(data)
