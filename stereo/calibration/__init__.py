"""Camera calibration (issue 15): plane targets, 3D test fields, zoom cameras and two-camera rigs.

Modules
-------
model
    The pinhole + Brown-Conrady camera model in pixels (OpenCV's definition).
dlt
    Starts with no initial guess: the 11-parameter DLT and its decomposition,
    plane-target homographies.
targets
    Chessboard detection and observation / field CSV files.
adjust
    The least-squares adjustment with self-calibration (robust, with covariances).
result
    :class:`Calibration`, the camera JSON (``camera_to_dict`` / ``camera_from_dict``).
zoom, rig, report, workflow
    Zoom models, stereo rigs, figures, and the one-call workflow of the CLI.
"""
