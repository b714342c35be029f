

def test_a_long_pass_logs_its_progress_where_no_terminal_shows_a_bar(caplog):
    """Issue 47: a batch job's log says how far a fit has got (a log line at every
    tenth of the pass's tasks once it has run ``after_s``), and a short pass says
    nothing."""
    import logging

    import dask

    from parammap.stages.fit import _LogProgress

    tasks = [dask.delayed(pow)(i, 2) for i in range(40)]
    with caplog.at_level(logging.INFO, logger="parammap"):
        with _LogProgress(after_s=0.0):
            dask.compute(*tasks, scheduler="synchronous")
    lines = [r.getMessage() for r in caplog.records if "% of the pass" in r.getMessage()]
    assert [int(m.split()[1]) for m in lines] == list(range(10, 101, 10)), lines
    assert lines[-1].startswith("fit: 100 % of the pass (40/40 tasks")
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="parammap"):
        with _LogProgress():
            dask.compute(*tasks, scheduler="synchronous")
    assert not [r for r in caplog.records if "% of the pass" in r.getMessage()]
