"""The package namespace: public names are functions, never shadowed by modules."""

import importlib
import types

import safestab


def test_simulate_is_the_function_before_and_after_importing_the_module():
    assert callable(safestab.simulate) and not isinstance(safestab.simulate, types.ModuleType)
    importlib.import_module("safestab.simulation")
    assert callable(safestab.simulate) and not isinstance(safestab.simulate, types.ModuleType)
    assert safestab.simulate is importlib.import_module("safestab.simulation").simulate


def test_no_public_name_is_a_module():
    for name in safestab.__all__:
        assert not isinstance(getattr(safestab, name), types.ModuleType), name
