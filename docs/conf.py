"""Sphinx configuration for the lsst_bfdrift documentation.

Build from the repository root with::

    python -m sphinx -W --keep-going -b html docs docs/_build/html
"""

import os
import sys

# Document the package in this source tree (not a copy installed elsewhere).
ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, ROOT)

import lsst_bfdrift  # noqa: E402

# -- Project information -----------------------------------------------------
project = "lsst_bfdrift"
author = "lsst_bfdrift developers"
copyright = "lsst_bfdrift developers"
release = lsst_bfdrift.__version__
version = ".".join(release.split(".")[:2])

# -- General configuration ---------------------------------------------------
extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "numpydoc",
]

exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
source_suffix = {".rst": "restructuredtext"}
root_doc = "index"
language = "en"
today_fmt = "%Y-%m-%d"

# Unresolved cross-references (e.g. numpy types named in docstrings) are not
# errors; every other warning is (the build runs with -W).
nitpicky = False

# Keep members in source order, the order the modules explain them in.
autodoc_member_order = "bysource"
autodoc_default_options = {
    "members": True,
}
# Signatures show parameters; types live in the numpydoc sections.
autodoc_typehints = "none"
autodoc_preserve_defaults = True

# numpydoc: render the Parameters/Returns/... sections. Class member tables
# are not generated (the members are documented by autodoc right below the
# class; a second summary table would only duplicate them).
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_attributes_as_param_list = True

# -- HTML output -------------------------------------------------------------
html_theme = "alabaster"
html_theme_options = {
    "description": "Electrostatic brighter-fatter model of thick CCDs",
    "fixed_sidebar": False,
}
html_static_path = ["_static"]
html_title = f"{project} {release}"
html_show_sourcelink = True


def _skip_lsst_members(app, what, name, obj, skip, options):
    """Leave out the members that lsst.pex.config / lsst.pipe.base define (config
    fields, connection descriptors, their sentinels): their docstrings are not
    numpydoc, and the package's configs are tabulated in the user guide."""
    module = getattr(type(obj), "__module__", "") or ""
    own = getattr(obj, "__module__", "") or ""
    if module.startswith(("lsst.pex", "lsst.pipe", "lsst.daf")) or \
            own.startswith(("lsst.pex", "lsst.pipe", "lsst.daf")):
        return True
    return None


def setup(app):
    app.connect("autodoc-skip-member", _skip_lsst_members)
