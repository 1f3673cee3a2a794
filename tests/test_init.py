"""The public API: the recipes first, loaded on first use; the lower layer beside them."""

from __future__ import annotations

import subprocess
import sys

import pytest

import antireplay

RECIPES = ["Receiver", "MavlinkGuard", "Initiator", "Responder", "EpochSigner", "EpochVerifier"]


@pytest.mark.parametrize("name", RECIPES)
def test_recipes_are_exported_and_load_on_first_use(name: str) -> None:
    assert name in antireplay.__all__
    assert getattr(antireplay, name).__name__ == name


def test_importing_the_package_loads_no_recipe() -> None:
    code = (
        "import sys, antireplay; "
        "print(sorted(m for m in ('antireplay.rcan.receive', 'antireplay.mavlink', "
        "'antireplay.pq.session', 'antireplay.epochs', 'pymavlink') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_unknown_names_are_attribute_errors() -> None:
    with pytest.raises(AttributeError, match="no attribute 'Nope'"):
        antireplay.Nope  # noqa: B018 - the access is the test
