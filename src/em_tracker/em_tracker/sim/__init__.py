"""The simulated rig around the simulated Aurora: the phantom's divots and the rig team's hands
(scripted calibration procedures), read through the host's real protocol path."""
