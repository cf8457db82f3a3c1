"""Fuses sparse SSD stereo depth with shape-from-shading depth into dense depth images."""
