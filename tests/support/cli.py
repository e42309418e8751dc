"""Run the `dcdi` command in-process: (exit code, stdout, stderr)."""
from dcdi_core.cli import main


def run_cli(capsys, *argv):
    try:
        code = main([str(a) for a in argv])
    except SystemExit as e:                  # argparse's own refusals
        code = e.code
    cap = capsys.readouterr()
    return code, cap.out, cap.err
