"""Hypothesis strategy for arbitrary valid board frames (shared by the codec and fuzz tests)."""

from __future__ import annotations

from hypothesis import strategies as st

from fbg_accel_driver.frame_codec import ADC_MAX, SEQ_MODULO, Frame

adc = st.integers(0, ADC_MAX)
frames = st.builds(
    Frame,
    seq=st.integers(0, SEQ_MODULO - 1),
    t_us=st.integers(0, 2**64 - 1),
    ref=adc,
    x=adc,
    y=adc,
    z=adc,
    temp_cc=st.integers(-(2**15), 2**15 - 1),
    status=st.integers(0, 255),
)
