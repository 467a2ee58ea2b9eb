"""The public API is documented and annotated, and `make docs` builds its reference.

Public = every name in ``__all__`` of ``fastsdf`` and of each of its modules whose name has no
leading underscore, plus the public methods and properties of public classes.
"""

import importlib
import inspect
import os
import pkgutil
import subprocess
import sys

import pytest

import fastsdf

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def public_modules():
    names = ["fastsdf"] + [
        m.name
        for m in pkgutil.walk_packages(fastsdf.__path__, "fastsdf.")
        if not any(p.startswith("_") for p in m.name.split(".")[1:])
    ]
    return [importlib.import_module(n) for n in names]


def public_objects():
    """``(qualified name, object)`` for every public function, class, method and property."""
    seen = set()
    for module in public_modules():
        for name in getattr(module, "__all__", []):
            obj = getattr(module, name)
            if not (inspect.isclass(obj) or inspect.isfunction(obj)) or id(obj) in seen:
                continue
            seen.add(id(obj))
            yield f"{module.__name__}.{name}", obj
            if inspect.isclass(obj):
                for attr, member in vars(obj).items():
                    if attr.startswith("_") and attr != "__init__":
                        continue
                    if inspect.isfunction(member) or isinstance(member, property):
                        yield f"{module.__name__}.{name}.{attr}", member


def test_every_public_module_has_a_docstring_and_all():
    for module in public_modules():
        assert inspect.getdoc(module), module.__name__
        assert hasattr(module, "__all__"), module.__name__
        for name in module.__all__:
            assert hasattr(module, name), f"{module.__name__}.{name} is in __all__ but missing"


def test_every_public_name_has_a_docstring():
    missing = [
        name
        for name, obj in public_objects()
        if not name.endswith(".__init__") and not inspect.getdoc(obj)
    ]
    assert not missing, missing


def test_every_public_function_is_annotated():
    missing = []
    for name, obj in public_objects():
        fn = obj.fget if isinstance(obj, property) else obj
        if not inspect.isfunction(fn):
            continue
        sig = inspect.signature(fn)
        params = [
            p.name
            for p in sig.parameters.values()
            if p.name not in ("self", "cls")
            and p.annotation is inspect.Parameter.empty
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        ]
        no_return = sig.return_annotation is inspect.Signature.empty and not name.endswith(
            ".__init__"
        )
        if params or no_return:
            missing.append(f"{name}({', '.join(params)}){' -> ?' if no_return else ''}")
    assert not missing, "\n".join(missing)


def test_package_ships_py_typed():
    assert os.path.exists(os.path.join(os.path.dirname(fastsdf.__file__), "py.typed"))
    with open(os.path.join(REPO, "setup.cfg"), encoding="utf-8") as fh:
        assert "py.typed" in fh.read()


@pytest.mark.slow
def test_pdoc_builds_the_api_reference(tmp_path):
    pytest.importorskip("pdoc")
    env = dict(os.environ, PYTHONPATH=REPO, MPLBACKEND="Agg")
    modules = [m.__name__ for m in public_modules()]
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "pdoc",
            "--docformat",
            "restructuredtext",
            "-o",
            str(tmp_path),
            *modules,
        ],
        capture_output=True,
        text=True,
        env=env,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr[-3000:]
    for page in (
        "fastsdf.html",
        "fastsdf/viz/render.html",
        "fastsdf/particles.html",
        "fastsdf/fields/grid.html",
    ):
        assert (tmp_path / page).exists(), page
    text = (tmp_path / "fastsdf" / "viz" / "render.html").read_text()
    assert "save_animation" in text and "animate" in text
