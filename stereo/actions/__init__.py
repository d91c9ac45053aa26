"""One module per ``stereo`` command, named as its ``stereo/cli`` module (``dense-rpc`` -> ``dense_rpc``).

One shape: the inputs and an options dataclass -> the action -> a frozen result whose ``summary_lines()``
are the lines the command prints. ``workspace`` owns the files of a pair job, ``scene`` renders the
synthetic scene of ``stereo demo``.
"""
