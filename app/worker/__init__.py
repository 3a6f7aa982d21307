"""Heavy work out of the real-time process (issue #37): the task service and its worker process.

``TaskService`` (service.py) is the application's side: submit a task, get its progress and its result or a
plain-words failure, cancel it; a crash of the worker is a failed task. The worker (process.py) runs the jobs of
jobs.py. Qt-free; the window's adapter is app/ui/tasks.py.
"""

from app.worker.service import Task, TaskFailed, TaskService, TaskStatus

__all__ = ["Task", "TaskFailed", "TaskService", "TaskStatus"]
