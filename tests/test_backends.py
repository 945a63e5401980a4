"""Correct on every backend (issue #39, part 1), checked on a CPU-only machine: no Dr.Jit or
Mitsuba type names a backend (types come from the active variant), the Mitsuba variant is
chosen in one place (``rt/drjit_setup.py``), and torch devices are named only where the
device is chosen (``torch_device.py``). The link level's device discipline is exercised in
tests/test_torch_device.py."""

import ast
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
SOURCES = [ROOT / "plugins" / "caviar_plugins", ROOT / "python" / "caviar"]
JIT_MODULES = {"dr", "drjit", "mi", "mitsuba"}
VARIANT_HOME = ROOT / "plugins" / "caviar_plugins" / "rt" / "drjit_setup.py"
DEVICE_HOMES = {ROOT / "plugins" / "caviar_plugins" / "torch_device.py",
                # training runs on the CPU by design (a script, not the loop)
                ROOT / "plugins" / "caviar_plugins" / "tools" / "training" / "train_yolo.py"}


def files():
    for base in SOURCES:
        yield from sorted(base.rglob("*.py"))


def strings(tree: ast.AST):
    """String constants that are code, not docstrings (strings standing alone)."""
    alone = {id(n.value) for n in ast.walk(tree) if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)}
    for n in ast.walk(tree):
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in alone:
            yield n


def backend_names(path: pathlib.Path) -> list[str]:
    tree = ast.parse(path.read_text())
    found = []
    for n in ast.walk(tree):
        if isinstance(n, ast.Attribute) and n.attr in ("llvm", "cuda", "metal") and \
                isinstance(n.value, ast.Name) and n.value.id in JIT_MODULES:
            found.append(f"{n.lineno}: {ast.unparse(n)}")
        if isinstance(n, (ast.Import, ast.ImportFrom)):
            names = [a.name for a in n.names] if isinstance(n, ast.Import) else [n.module or ""]
            found += [f"{n.lineno}: import {m}" for m in names
                      if m.split(".")[0] == "drjit" and any(p in ("llvm", "cuda") for p in m.split("."))]
    if path != VARIANT_HOME:
        found += [f"{n.lineno}: {n.value!r}" for n in strings(tree)
                  if n.value.startswith(("llvm_ad", "cuda_ad", "scalar_rgb", "llvm_mono", "cuda_mono"))]
    if path not in DEVICE_HOMES:
        found += [f"{n.lineno}: device {n.value!r}" for n in strings(tree)
                  if n.value in ("cpu", "cuda", "mps") or n.value.startswith("cuda:")]
    return found


def test_no_code_names_a_backend_or_a_device_outside_where_it_is_chosen():
    offenders = [f"{p.relative_to(ROOT)}:{f}" for p in files() for f in backend_names(p)]
    assert not offenders, "\n".join(offenders)


def test_the_check_sees_the_mistakes_of_the_h100(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text("import drjit as dr\nimport torch\n\ndef f(x, m):\n    lam = dr.llvm.ad.Float64(x)\n"
                   "    t = torch.from_numpy(m).to('cpu')\n    mi.set_variant('llvm_ad_rgb')\n    return lam, t\n")
    assert [f.split(": ", 1)[1] for f in backend_names(bad)] == ["dr.llvm", "'llvm_ad_rgb'",
                                                                  "device 'cpu'"]


def test_onnx_models_use_cuda_where_onnxruntime_has_it_and_say_when_a_gpu_goes_unused():
    from caviar_plugins.vision.yolo import execution_providers

    assert execution_providers(["CUDAExecutionProvider", "CPUExecutionProvider"], gpu=True) == (
        ["CUDAExecutionProvider", "CPUExecutionProvider"], None)
    providers, note = execution_providers(["CPUExecutionProvider"], gpu=True)
    assert providers == ["CPUExecutionProvider"] and "install onnxruntime-gpu" in note
    assert execution_providers(["CPUExecutionProvider"], gpu=False) == (["CPUExecutionProvider"], None)
