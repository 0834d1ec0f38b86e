"""Shared test settings. ``PMSM_SLOW=full`` selects the long form of tests marked ``slow``;
``make test`` runs them in their short form."""

import os

import pytest


@pytest.fixture(scope="session")
def full_form() -> bool:
    return os.environ.get("PMSM_SLOW", "").lower() == "full"
