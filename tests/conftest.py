"""Test-wide settings: flexmbs's own DeprecationWarnings are errors.

A library module that still calls a deprecated spelling (the warning attributed to a flexmbs
module), and a test that calls simulate's former keywords or reads Result.settings by key, fail;
a test checking the old spelling catches its warning with pytest.warns (which records every
warning, these filters aside)."""

_ERRORS = (
    "error::DeprecationWarning:flexmbs",
    r"error:(simulate|simulate_for_adjoint|memory_estimate|simulate_with_error)\(.*\) is "
    r"deprecated:DeprecationWarning",
    r"error:Result\.settings\[.*\] is deprecated:DeprecationWarning",
)


def pytest_configure(config):
    for line in _ERRORS:
        config.addinivalue_line("filterwarnings", line)
