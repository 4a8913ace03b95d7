"""MkDocs hook: generate ``validation.md`` from ``benchmarks/results/*.json`` at build time.

Each JSON file becomes one section (:mod:`benchmark_summary`); a new file appears at the
next build without any edit. A file that cannot be read, and a figure outside its
credible range whose file does not say why, are warnings, which fail a
``mkdocs build --strict``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import benchmark_summary  # beside this file: MkDocs puts the hook's folder on sys.path while loading it
from mkdocs.structure.files import File

log = logging.getLogger("mkdocs.hooks.validation")

#: The benchmarks' results, relative to the folder of mkdocs.yml.
RESULTS = "benchmarks/results"
#: The generated page's path inside the site's docs.
PAGE = "validation.md"


def validation_markdown(root) -> str:
    """The validation page for the repository at ``root``.

    Parameters
    ----------
    root : str or Path
        The folder holding ``benchmarks/results/``.

    Returns
    -------
    str
        Markdown; unreadable files are logged as warnings and left out.
    """
    results = Path(root) / RESULTS
    summaries = []
    for path in sorted(results.glob("*.json")):
        try:
            summaries.append(benchmark_summary.summarise(path))
        except (OSError, ValueError) as err:
            log.warning("validation page: %s", err)
            continue
        for line in summaries[-1].unexplained:  # a figure outside its credible range must say why
            log.warning("validation page: %s", line)
    if not summaries:
        log.warning("validation page: no JSON file in %s", results)
    return benchmark_summary.page(summaries, RESULTS)


def on_files(files, config):
    """Add the generated ``validation.md`` to the site's files."""
    root = Path(config.config_file_path).parent
    if files.get_file_from_path(PAGE) is not None:
        log.warning("validation page: docs/%s exists, but the page is generated; remove the file", PAGE)
        return files
    files.append(File.generated(config, PAGE, content=validation_markdown(root)))
    return files
