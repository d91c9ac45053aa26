"""Pixels to observations on the stereo side: block tie-point tracks (``tracks``) and chessboard targets
(``targets``).
"""
