"""The FMUs from Python: the modelDescription.xml reader, the build, the FMI binding, the co-simulation master,
and the analytic linear model that checks the plant FMU."""
