"""The trainers of the shipped weights (one module per registry entry); each writes into its entry's folder."""
