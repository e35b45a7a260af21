"""Reference estimators in Python: FilterPy UKF and CasADi/Ipopt MHE over any DiscreteModel."""
