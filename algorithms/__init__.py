"""Hand-written learning and tuning algorithms (A2C, RMSProp eq. 32, GA, NSGA-II)."""
