"""One module per ``rectify`` command, named as its ``rectify/cli`` module.

One shape: an options dataclass (its defaults are the command-line defaults) -> the action (the job's
:class:`~rectify.actions.workspace.Workspace`, the paths, the options) -> a frozen result whose
``summary_lines()`` are the lines the command prints. ``workspace`` owns the files of one job.
"""
