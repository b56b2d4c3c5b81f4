"""ASAM's own quality checkers run on exported scenarios: ``asam-qc-openscenarioxml`` on ``.xosc`` files (schema,
references to entities, storyboard elements and the road network, data types) and ``asam-qc-opendrive`` on
``.xodr`` files (schema, lane and junction semantics, geometry, smoothness).

They run in this process through their own ``run_checks`` (what their ``qc_openscenario`` / ``qc_opendrive`` command
lines call), with their log output held back; the schemas they validate against ship inside their wheels, so
nothing is fetched. A file *passes* when no checker reports an issue of level ERROR, no checker ended in an ERROR
status, and the schema checker ran (a schema check skipped because a basic check failed is not a pass).
"""
from __future__ import annotations

import contextlib
import logging
from dataclasses import dataclass
from pathlib import Path

from omniscs.errors import OmniscsError

#: The checker bundles: file suffix -> (package, module, bundle name, schema checker id).
BUNDLES = {".xosc": ("asam-qc-openscenarioxml", "qc_openscenario", "xoscBundle", "valid_schema"),
           ".xodr": ("asam-qc-opendrive", "qc_opendrive", "xodrBundle", "valid_schema")}
#: Issue descriptions kept per report (the counts are always complete).
KEPT_MESSAGES = 5


@dataclass(frozen=True)
class CheckReport:
    """What one ASAM checker bundle said about one file."""

    file: str
    """The checked file."""
    checker: str
    """The checker package and its version, e.g. ``asam-qc-opendrive 1.0.0``."""
    issues: dict
    """Issue counts by level: {"error": n, "warning": n, "information": n}."""
    checkers: dict
    """Checker counts by final status: {"completed": n, "skipped": n, "error": n}."""
    schema_checked: bool
    """Whether the schema checker ran to completion."""
    messages: tuple[str, ...]
    """The first issue descriptions of level ERROR or WARNING (``checker_id: description``)."""

    @property
    def passed(self) -> bool:
        return self.issues["error"] == 0 and self.checkers["error"] == 0 and self.schema_checked

    def to_dict(self) -> dict:
        return {"file": self.file, "checker": self.checker, "issues": dict(self.issues),
                "checkers": dict(self.checkers), "schema_checked": self.schema_checked,
                "messages": list(self.messages), "passed": self.passed}


def checker_versions() -> dict[str, str]:
    """{package: version} of the installed ASAM checkers; an OmniscsError naming what to install when missing."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for package, *_ in BUNDLES.values():
        try:
            out[package] = version(package)
        except PackageNotFoundError:
            raise OmniscsError(f"{package} is not installed; install it (`pip install {package}`, or `make setup`, "
                               "which installs the test extra) to check exported scenarios") from None
    return out


@contextlib.contextmanager
def _quiet_logging():
    """The checkers configure the root logger when imported and log every step at INFO: keep that out of ours."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    logging.disable(logging.CRITICAL)
    try:
        yield
    finally:
        logging.disable(logging.NOTSET)
        root.handlers[:] = handlers
        root.setLevel(level)


def check_file(path: str | Path) -> CheckReport:
    """Run the ASAM checker bundle of a ``.xosc`` or ``.xodr`` file on it."""
    import importlib

    path = Path(path)
    if path.suffix not in BUNDLES:
        raise OmniscsError(f"{path} is neither an OpenSCENARIO (.xosc) nor an OpenDRIVE (.xodr) file")
    if not path.is_file():
        raise OmniscsError(f"{path} does not exist; export the scenario first")
    package, module, bundle, schema_id = BUNDLES[path.suffix]
    versions = checker_versions()
    with _quiet_logging():
        main = importlib.import_module(f"{module}.main")
        constants = importlib.import_module(f"{module}.constants")
        from qc_baselib import Configuration, Result

        config = Configuration()
        config.set_config_param("InputFile", str(path.resolve()))
        config.register_checker_bundle(bundle)
        result = Result()
        result.register_checker_bundle(name=bundle, description=f"{bundle} run by omniscs",
                                       version=constants.BUNDLE_VERSION, summary="")
        result.set_result_version(version=constants.BUNDLE_VERSION)
        main.run_checks(config, result)
    issues = {"error": 0, "warning": 0, "information": 0}
    statuses = {"completed": 0, "skipped": 0, "error": 0}
    messages, schema_checked = [], False
    for checker in result.get_checker_results(bundle):
        status = getattr(checker.status, "value", str(checker.status))
        statuses[status] = statuses.get(status, 0) + 1
        if checker.checker_id.endswith(schema_id) and status == "completed":
            schema_checked = True
        if status == "error":
            messages.append(f"{checker.checker_id}: {checker.summary}")
        for issue in checker.issues:
            level = issue.level.name.lower()
            issues[level] = issues.get(level, 0) + 1
            if level in ("error", "warning"):
                messages.append(f"{checker.checker_id}: {issue.description}")
    return CheckReport(str(path), f"{package} {versions[package]}", issues, statuses, schema_checked,
                       tuple(messages[:KEPT_MESSAGES]))
