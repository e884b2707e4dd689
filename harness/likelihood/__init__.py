"""The likelihood engine: the rig as a stochastic model scored by the one-step-ahead prediction errors of a Kalman
filter run through each record (the prediction-error method; CTSM-R's layout, one small module each):

- :mod:`.model`: the stochastic model in continuous time (the plant's equations, the DAQ's sensors, process noise on
  the hub's and the link's torques, measurement noise) and its exact discretisation;
- :mod:`.record`: a record as the filter reads it (command, readings, which samples measure);
- :mod:`.kalman`: the filter (a compiled loop, ``fmus/master/kalman.c``) and the Rauch-Tung-Striebel smoother;
- :mod:`.fit`: parameters by maximum likelihood over the records of one unit, intervals from the Fisher information;
- :mod:`.force`: the missing force, a random-walk torque on the hub, smoothed through each record; :mod:`.traces`
  its traces stored (force_picture.parquet);
- :mod:`.unit`: a run directory through the engine, and what its fit finds.
"""
