"""Dynamic calibration: the excitation plan, a tone's amplitude, phase, delay and budget, the chain model,
the orchestration of a run, the checks of an applied dynamic calibration and the Bode plot."""
