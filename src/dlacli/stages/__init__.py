"""Stages: plain functions from inputs to outputs."""
