"""Data from the rig: excitation signals, campaigns on the FMU twin, and real records imported."""
