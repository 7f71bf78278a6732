"""Integration: `simulate` and what it is made of (the solve, its options, its failures)."""

from .simulate import simulate as simulate
