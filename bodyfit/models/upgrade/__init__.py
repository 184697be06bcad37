"""Upgrading SMPL-format motion to biomechanical coordinates (DESIGN.md section 7): readers of AMASS-style
sequences and SMPL-family model files, the SMPL forward pass, and the upgrade itself."""
