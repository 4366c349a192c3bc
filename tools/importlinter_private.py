"""An import-linter contract: no package imports another package's private modules.

``robocal.identification`` may import ``robocal.kinematics`` (its public face, the package
``__init__``) but not ``robocal.kinematics._model``: what a package keeps behind an underscore
may change without notice to its neighbours. Listed packages (``allow``) are shared
foundations whose modules every layer may use (``robocal._core``).

Registered in pyproject.toml under ``contract_types``; ``lint-imports`` finds this module
because ``.ci/run`` and the test put ``tools/`` on ``PYTHONPATH``.
"""

from __future__ import annotations

from grimp import ImportGraph
from importlinter import Contract, ContractCheck, fields, output


class PrivateModulesContract(Contract):
    """``root``: the top-level package; ``allow``: packages whose private modules are shared."""

    root = fields.StringField()
    allow = fields.ListField(subfield=fields.StringField(), required=False)

    def check(self, graph: ImportGraph, verbose: bool) -> ContractCheck:
        root = str(self.root)  # type: ignore[attr-defined]
        allow = set(self.allow or [])  # type: ignore[attr-defined]
        broken: list[tuple[str, str]] = []
        for importer in sorted(graph.modules):
            parts = importer.split(".")
            if parts[0] != root or len(parts) < 2:
                continue
            for imported in sorted(graph.find_modules_directly_imported_by(importer)):
                target = imported.split(".")
                if target[0] != root or len(target) < 3 or target[1] == parts[1]:
                    continue
                if ".".join(target[:2]) in allow:
                    continue
                if any(t.startswith("_") and not t.startswith("__") for t in target[2:]):
                    broken.append((importer, imported))
        return ContractCheck(kept=not broken, metadata={"broken": broken})

    def render_broken_contract(self, check: ContractCheck) -> None:
        for importer, imported in check.metadata["broken"]:
            output.print_error(f"{importer} imports the private module {imported}")
            output.new_line()
