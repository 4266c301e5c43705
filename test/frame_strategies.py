"""Hypothesis strategies for arbitrary valid board frames, v1 and v2 (shared by the codec and fuzz tests)."""

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
# Version-2 frames: the version-1 fields + a 12-bit aux count.
frames_v2 = st.builds(lambda f, aux: Frame(f.seq, f.t_us, f.ref, f.x, f.y, f.z, f.temp_cc, f.status, aux), frames, adc)
