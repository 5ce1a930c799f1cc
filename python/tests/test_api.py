"""The public surface: names, type stubs that cover the native module, docstrings."""

import ast
import pathlib

import spintune
import spintune._core as core


def stub_tree():
    path = pathlib.Path(spintune.__file__).with_name("_core.pyi")
    assert path.is_file(), "the type stubs are installed with the package"
    return ast.parse(path.read_text())


def test_stubs_cover_the_native_module():
    tree = stub_tree()
    top = {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            top[node.name] = node
        elif isinstance(node, ast.AnnAssign):
            top[node.target.id] = node
    public = [n for n in dir(core) if not n.startswith("_") or n == "__version__"]
    missing = [n for n in public if n not in top]
    assert not missing, missing
    for name, node in top.items():
        if isinstance(node, ast.ClassDef):
            stubbed = {b.name for b in node.body if isinstance(b, ast.FunctionDef)}
            actual = {m for m in dir(getattr(core, name)) if not m.startswith("_")}
            assert actual <= stubbed, (name, actual - stubbed)
    assert (pathlib.Path(spintune.__file__).with_name("py.typed")).is_file()


def test_public_names_and_docstrings_with_units():
    for name in ["KalmanGradient", "newton_step", "SimulationRun", "ArraySimulation", "RunSession", "SimulatedDevice",
                 "open_store", "default_config", "paper_config", "resolve_config", "resolve_tuner_config"]:
        obj = getattr(spintune, name)
        assert obj.__doc__ and len(obj.__doc__) > 40, name
    assert spintune.KalmanGradient.__module__ == "spintune"
    assert "mV" in spintune.KalmanGradient.__doc__ and "mV" in spintune.newton_step.__doc__
    assert "mV" in spintune.KalmanGradient.update.__doc__
    assert "µV" in spintune.SimulationRun.__doc__ and "ns" in spintune.SimulationRun.__doc__
    assert "µV" in spintune.ArraySimulation.__doc__ and "ns" in spintune.ArraySimulation.__doc__
    assert "µV" in spintune.ArraySimulation.truth.__doc__ and "truth" in spintune.ArraySimulation.truth.__doc__
    assert spintune.PROTOCOL_VERSION == 4  # protocol v4: batches (array runs)
    import spintune.qcodes as sq

    assert "mV" in sq.__doc__ and "paused" in sq.__doc__
