"""psl_cli.progress.LearnProgress: plain lines per finished task when not on a terminal (with
the graph's per-batch feedback turned into per-task counts), one tqdm bar when on one."""
import io

from psl_cli.progress import LearnProgress


def lines_of(progress: LearnProgress) -> list[str]:
    return progress.stream.getvalue().splitlines()


def test_batch_mode_writes_one_line_per_finished_task():
    progress = LearnProgress(3, stream=io.StringIO())
    progress.finished(0, -0.005, True, in_all=1, rollouts=1)
    progress.finished(1, -1.25, False, in_all=41, rollouts=40)
    progress.close(complete=False)
    assert lines_of(progress) == [
        'task 1/3 fulfilled: best reward -0.005, 1 rollouts (1 in all)',
        'task 2/3 NOT fulfilled: best reward -1.250, 40 rollouts (41 in all)']


def test_graph_feedback_becomes_one_line_per_task_with_its_own_rollouts():
    """Feedback per CMA-ES batch (task index, rollouts in all, best, fulfilled): a task is
    finished by the feedback of the next one, the last one by the session's end."""
    progress = LearnProgress(2, stream=io.StringIO())
    for fb in [(0, 10, -0.5, False), (0, 20, -0.3, False), (0, 21, -0.004, True),
               (1, 22, -0.006, True)]:
        progress.batch(*fb)
    assert lines_of(progress) == ['task 1/2 fulfilled: best reward -0.004, 21 rollouts '
                                  '(21 in all)']
    progress.close(complete=True)
    assert lines_of(progress)[1:] == ['task 2/2 fulfilled: best reward -0.006, 1 rollouts '
                                      '(22 in all)']


def test_a_resumed_graph_session_counts_its_first_task_in_all_only():
    """Tasks 0..1 came from the checkpoint: the rollouts of task 2 alone are not known."""
    progress = LearnProgress(4, stream=io.StringIO())
    progress.batch(2, 35, -0.2, False)
    progress.batch(3, 36, -0.01, True)
    progress.close(complete=False)          # cancelled during task 3: it is not finished
    assert lines_of(progress) == ['task 3/4 NOT fulfilled: best reward -0.200, 35 rollouts '
                                  'in all']


def test_on_a_terminal_it_draws_one_bar_and_no_lines():
    progress = LearnProgress(2, stream=io.StringIO(), bar=True)
    progress.batch(0, 10, -0.5, False)
    progress.batch(1, 11, -0.01, True)
    progress.close(complete=True)
    text = progress.stream.getvalue()
    assert '\r' in text and '2/2' in text and '100%' in text
    assert 'task 1/2 ' not in text         # the plain lines are not written


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_bar_is_drawn_when_the_stream_is_a_terminal_and_only_then():
    on_terminal = LearnProgress(1, stream=Terminal())
    on_terminal.finished(0, -0.1, True, in_all=3, rollouts=3)
    on_terminal.close(complete=True)
    assert '\r' in on_terminal.stream.getvalue()
    in_a_file = LearnProgress(1, stream=io.StringIO())
    in_a_file.finished(0, -0.1, True, in_all=3, rollouts=3)
    assert '\r' not in in_a_file.stream.getvalue()
