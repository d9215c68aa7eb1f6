from pipeline.utc import utc_span, utc_text

T = 1_793_491_200_123_456_789  # 2026-11-01 00:00:00.123456789 UTC


def test_utc_text_and_span():
    assert utc_text(T) == "2026-11-01 00:00:00.123 UTC"
    assert utc_span(T, T + 5_400 * 10**9) == "2026-11-01 00:00:00.123 .. 01:30:00.123 UTC"  # the date said once
    assert utc_span(T, T + 86_400 * 10**9) == "2026-11-01 00:00:00.123 .. 2026-11-02 00:00:00.123 UTC"
