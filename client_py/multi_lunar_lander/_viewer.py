"""The "human" render mode: a pygame window showing the server's RGB frames at render_fps."""

from __future__ import annotations

import numpy as np


class Viewer:
    def __init__(self, title: str, fps: int):
        try:
            import pygame
        except ImportError as error:  # An optional dependency (extra "render").
            raise ImportError(
                'render_mode="human" needs pygame: pip install "pygame>=2.1.3" (the package\'s `render` extra)'
            ) from error
        self._pygame = pygame
        self._title = title
        self._fps = fps
        self._screen = None
        self._clock = None

    def show(self, frame: np.ndarray) -> None:
        pygame = self._pygame
        height, width, _ = frame.shape
        if self._screen is None:
            pygame.display.init()
            pygame.display.set_caption(self._title)
            self._screen = pygame.display.set_mode((width, height))
            self._clock = pygame.time.Clock()
        # surfarray is indexed [x][y]; frames are [row][column].
        pygame.surfarray.blit_array(self._screen, np.ascontiguousarray(frame.transpose(1, 0, 2)))
        pygame.event.pump()
        pygame.display.flip()
        self._clock.tick(self._fps)

    def close(self) -> None:
        if self._screen is not None:
            self._pygame.display.quit()
            self._screen = None
