"""Stereo image coding by watermarking (thesis chapter 6): the rectified left image
carries its disparity, so one image transmits the stereo pair."""
