"""Safety-critical scenario synthesis: behaviour-level variants (``omniscs.scs.behavior``)."""
