"""Compiled inner loops (numba) and the thread pools they share: the regressor's lanes (eqs.
10-18), the zero-phase filter's columns, the payload projection's barrier method. Each is checked
against a plain reference (scipy, Pinocchio) in the tests."""
