"""Camera calibration (issue 15): plane targets, 3D test fields, zoom cameras and two-camera rigs.

Modules
-------
model
    The pinhole + Brown-Conrady camera model in pixels (OpenCV's definition).
dlt
    Starts with no initial guess: the 11-parameter DLT and its decomposition,
    plane-target homographies.
views
    :class:`TargetView`: the measured target points of one image (chessboard detection is in
    ``stereo.features.targets``, the observation / field CSV files in ``stereo.formats.calibration``).
adjust
    The least-squares adjustment with self-calibration (robust, with covariances).
result
    :class:`Calibration` (its camera JSON: ``rectify.formats.camera.intrinsics_document``, read back by
    ``stereo.formats.calibration.camera_from_dict``).
zoom, rig, report, workflow
    Zoom models, stereo rigs, figures, and the one-call workflow of the CLI.
"""
