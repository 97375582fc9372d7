"""The ``bfdrift`` command line: one subcommand per job, each a thin
wrapper over the functions of the stages before it.
"""


from lsst_bfdrift.cli.main import main  # noqa: F401

__all__ = ["main"]
