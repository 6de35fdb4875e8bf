"""The shape of the code: which package may import which, and no import cycle.

Read from the sources (every import statement, also those inside functions), not from a
running interpreter, so a lazy import counts as much as one at the top of a module.
"""
import ast
import re
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'src'
PACKAGES = sorted(p.name for p in SRC.iterdir() if (p / 'package.xml').is_file())
PYTHON_PACKAGES = [p for p in PACKAGES if (SRC / p / p).is_dir()]
# what the design card (../shared/DESIGN.md, section 3a) keeps apart
FORBIDDEN = {
    'psl_task': {'psl_ros', 'psl_sim', 'psl_controller', 'psl_optimizer', 'psl_memory',
                 'psl_bench', 'psl_cli'},
    'psl_memory': {'psl_task', 'psl_sim', 'psl_controller', 'psl_optimizer', 'psl_bench',
                   'psl_cli'},
    'psl_ros': {'psl_task', 'psl_sim', 'psl_controller', 'psl_optimizer', 'psl_memory',
                'psl_bench', 'psl_cli'},
    # the controller is a library the robots run (psl's standard robot runs its trajectory
    # controller in its own loop); it knows no simulator
    'psl_controller': {'psl_sim', 'psl_optimizer', 'psl_memory', 'psl_bench', 'psl_cli'},
    'psl_sim': {'psl_optimizer', 'psl_memory', 'psl_bench', 'psl_cli'},
    'psl_optimizer': {'psl_bench', 'psl_cli'},
    'psl_bench': {'psl_cli'},
}


def modules() -> dict[str, Path]:
    """Dotted module name -> file, for every module of the workspace's Python packages."""
    out = {}
    for package in PYTHON_PACKAGES:
        for path in sorted((SRC / package / package).rglob('*.py')):
            parts = path.relative_to(SRC / package).with_suffix('').parts
            name = '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)
            out[name] = path
    return out


MODULES = modules()


def imports_of(path: Path) -> set[str]:
    """The workspace modules a file imports (``from pkg import mod`` names the module)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [f'{node.module}.{alias.name}' for alias in node.names] + [node.module]
        else:
            continue
        for name in names:
            while name and name not in MODULES:
                name = name.rpartition('.')[0]
            if name:
                found.add(name)
    return found


GRAPH = {name: imports_of(path) - {name} for name, path in MODULES.items()}


def test_the_sources_are_found():
    assert {'psl_memory', 'psl_ros', 'psl_sim', 'psl_bench', 'psl_cli'} <= set(PYTHON_PACKAGES)
    assert 'psl_memory.skill_memory' in MODULES and 'psl_ros.client' in MODULES
    assert 'psl_optimizer.reward' in GRAPH['psl_optimizer.batch_rollout']


@pytest.mark.parametrize('package', sorted(FORBIDDEN))
def test_a_package_imports_none_of_the_packages_above_it(package):
    wrong = sorted(f'{module} imports {target}'
                   for module, targets in GRAPH.items() if module.split('.')[0] == package
                   for target in targets if target.split('.')[0] in FORBIDDEN[package])
    assert not wrong, wrong


def test_no_import_cycle_among_the_modules():
    """Depth-first search for a back edge; the message shows one cycle."""
    state: dict[str, int] = {}          # 1 = on the current path, 2 = done
    path: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        path.append(module)
        for target in sorted(GRAPH[module]):
            if state.get(target) == 1:
                return path[path.index(target):] + [target]
            if target not in state:
                cycle = visit(target)
                if cycle:
                    return cycle
        state[module] = 2
        path.pop()
        return None

    for module in sorted(GRAPH):
        if module not in state:
            cycle = visit(module)
            assert cycle is None, ' -> '.join(cycle)


@pytest.mark.parametrize('package', PYTHON_PACKAGES)
def test_package_xml_declares_every_workspace_package_the_code_imports(package):
    declared = set(re.findall(r'<(?:exec_|build_|test_)?depend>(\w+)</',
                              (SRC / package / 'package.xml').read_text()))
    used = {target.split('.')[0] for module, targets in GRAPH.items()
            if module.split('.')[0] == package for target in targets} - {package}
    assert used <= declared, f'{package}/package.xml lacks {sorted(used - declared)}'
