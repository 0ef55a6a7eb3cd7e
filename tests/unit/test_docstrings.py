"""The numpydoc ``Examples`` of every ctsplat module run as doctests (in a temporary folder: some write files).

Examples that need a finished workflow's outputs (``results/...``) are marked ``# doctest: +SKIP``.
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import ctsplat

MODULES = sorted(m.name for m in pkgutil.walk_packages(ctsplat.__path__, prefix="ctsplat.")
                 if not m.name.split(".")[-1].startswith("__"))


@pytest.mark.parametrize("name", MODULES)
def test_docstring_examples_run(name: str, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    module = importlib.import_module(name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} docstring examples of {name} failed"
