"""Upgrading SMPL-format motion to biomechanical coordinates (user guide: docs/upgrade.md): readers of
AMASS-style sequences and SMPL-family model files, the SMPL forward pass, and the upgrade itself.

SMPL: M. Loper, N. Mahmood, J. Romero, G. Pons-Moll and M. J. Black, "SMPL: A Skinned Multi-Person Linear
Model", ACM Transactions on Graphics 34(6) (SIGGRAPH Asia), 2015. AMASS: N. Mahmood, N. Ghorbani, N. F. Troje,
G. Pons-Moll and M. J. Black, "AMASS: Archive of Motion Capture as Surface Shapes", IEEE/CVF International
Conference on Computer Vision (ICCV), 2019.
"""
