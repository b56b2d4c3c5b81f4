"""Evaluation of driving models on generated datasets: nuScenes detection metrics (``detection``) and UniAD's
planning metrics (``planning``), on the formats those projects read and write (``nuscenes_io``)."""
