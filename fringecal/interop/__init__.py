"""Exchange of calibrations with other software (pure: never imports prefect).

:mod:`fringecal.interop.opencv` converts one sensor to and from OpenCV's pinhole model
(camera matrix, distortion coefficients, world -> camera pose) and measures the
model difference in pixels; :mod:`fringecal.interop.opencv_storage` writes and reads
a scanner as OpenCV ``FileStorage`` YAML in the layout of ``cv2.stereoCalibrate``.
"""
