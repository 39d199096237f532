"""The real UR3 (through ur_rtde) and a frame grabber, behind the same Robot and Imager
protocols as the twin. The only package that imports ur_rtde and cv2."""
