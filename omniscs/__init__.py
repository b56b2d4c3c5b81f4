"""OmniSCS: safety-critical driving scenarios from ordinary logs (domain library, free of Prefect)."""
__version__ = "0.1.0"
