"""The numerical core of armid: Khosla's linear-in-parameters Newton-Euler model and identification."""
