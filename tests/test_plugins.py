"""Plugin discovery by entry point and import path, and the errors for unknown names."""

import pytest

from slam import plugins
from slam.errors import PluginError


def test_builtin_plugins_are_registered():
    assert {"floam", "improved_floam"} <= set(plugins.available("slam.frontends"))
    assert {"isam2", "batch"} <= set(plugins.available("slam.backends"))
    assert {"prior", "odometry", "position", "loop_closure"} <= set(
        plugins.available("slam.factors")
    )


def test_unknown_plugin_lists_available():
    with pytest.raises(PluginError) as err:
        plugins.load("slam.backends", "isam3")
    assert "isam2" in str(err.value) and "batch" in str(err.value)


def test_import_path_errors_are_clear():
    with pytest.raises(PluginError, match="cannot import"):
        plugins.load("slam.factors", "no_such_pkg.mod:Thing")
    with pytest.raises(PluginError, match="has no attribute"):
        plugins.load("slam.factors", "slam.factors:NoSuchThing")
    assert plugins.load("slam.factors", "slam.factors:GraphView").__name__ == "GraphView"
