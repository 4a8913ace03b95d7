"""Spheres and planes in point clouds: fits, outlier rejection, reference data,
sphere-plate analysis and labelling against an artefact definition."""
