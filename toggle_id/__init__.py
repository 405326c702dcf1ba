"""toggle-id: identification of a motor-toggle clamping unit (Hsu, Huang, Fung 2016) and residual-driven model discovery."""

__version__ = "0.1.0"
