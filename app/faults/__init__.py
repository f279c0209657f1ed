"""Fault isolation: diagnoses, fault detections and clearances, faults still open."""
